/* TCP for the C reference target (PROTOCOL.md section 10.5): listen, accept, dial.
 * POSIX sockets only. Each function says what failed in one line on stderr. */
#ifndef HIL_NET_H
#define HIL_NET_H

#include <signal.h>
#include <stddef.h>

/* A socket listening on `addr` (host:port, a tcp/ prefix accepted) for harnesses;
 * -1 with one line on stderr when it cannot (for example the port is in use). */
int net_listen(const char *addr);

/* The next harness on `ls` (its address in `peer`), with TCP_NODELAY and receive
 * timestamps on; -1 once *stop is set or on an error. */
int net_accept(int ls, char *peer, size_t peer_size, volatile sig_atomic_t *stop);

/* A connection to the harness at `addr`, retried every 50 ms for 30 s (`forever`:
 * until *stop), with TCP_NODELAY and receive timestamps on; -1 on failure. */
int net_dial(const char *addr, int forever, volatile sig_atomic_t *stop);

/* TCP_NODELAY and SO_TIMESTAMPNS on a connected socket. */
void net_tune(int fd);

#endif
