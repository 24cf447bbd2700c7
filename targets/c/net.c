/* TCP for the C reference target: listen, accept, dial (net.h). */
#define _POSIX_C_SOURCE 200809L
#include "net.h"

#include <errno.h>
#include <netdb.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <stdio.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

static int split_address(const char *text, char *host, size_t host_size, const char **port) {
    if (strncmp(text, "tcp/", 4) == 0) text += 4;
    const char *colon = strrchr(text, ':');
    if (!colon || colon == text || (size_t)(colon - text) >= host_size || !colon[1]) return -1;
    memcpy(host, text, (size_t)(colon - text));
    host[colon - text] = '\0';
    if (host[0] == '[' && host[strlen(host) - 1] == ']') {
        memmove(host, host + 1, strlen(host));
        host[strlen(host) - 1] = '\0';
    }
    *port = colon + 1;
    return 0;
}

static struct addrinfo *resolve(const char *addr, int passive) {
    char host[256];
    const char *port;
    if (split_address(addr, host, sizeof host, &port) != 0) {
        fprintf(stderr, "hil_target: bad address %s: expected host:port, e.g. 127.0.0.1:7600\n", addr);
        return NULL;
    }
    struct addrinfo hints, *ai = NULL;
    memset(&hints, 0, sizeof hints);
    hints.ai_socktype = SOCK_STREAM;
    hints.ai_flags = passive ? AI_PASSIVE : 0;
    int rc = getaddrinfo(host, port, &hints, &ai);
    if (rc != 0) {
        fprintf(stderr, "hil_target: cannot resolve %s: %s\n", addr, gai_strerror(rc));
        return NULL;
    }
    return ai;
}

/* A socket listening on `addr` for harnesses; -1 with one line on stderr when it
 * cannot (for example the port is in use). */
int net_listen(const char *addr) {
    struct addrinfo *ai = resolve(addr, 1);
    if (!ai) return -1;
    int one = 1, ls = socket(ai->ai_family, ai->ai_socktype, ai->ai_protocol);
    if (ls >= 0) setsockopt(ls, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
    if (ls < 0 || bind(ls, ai->ai_addr, ai->ai_addrlen) != 0 || listen(ls, 4) != 0) {
        int err = errno;
        fprintf(stderr, "hil_target: cannot listen on %s: %s%s\n", addr, strerror(err),
                err == EADDRINUSE ? " (another target, or another run?)" : "");
        if (ls >= 0) close(ls);
        ls = -1;
    }
    freeaddrinfo(ai);
    return ls;
}

void net_tune(int fd) {
    int one = 1;
    setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
#ifdef SO_TIMESTAMPNS
    setsockopt(fd, SOL_SOCKET, SO_TIMESTAMPNS, &one, sizeof one);
#endif
}

/* The next harness on `ls` (its address in `peer`); -1 on SIGTERM or an error. */
int net_accept(int ls, char *peer, size_t peer_size, volatile sig_atomic_t *stop) {
    while (!*stop) {
        struct sockaddr_storage sa;
        socklen_t len = sizeof sa;
        int fd = accept(ls, (struct sockaddr *)&sa, &len);
        if (fd < 0 && errno == EINTR) continue;
        if (fd < 0) {
            fprintf(stderr, "hil_target: cannot accept a harness: %s\n", strerror(errno));
            return -1;
        }
        char host[256], port[32];
        if (getnameinfo((struct sockaddr *)&sa, len, host, sizeof host, port, sizeof port,
                        NI_NUMERICHOST | NI_NUMERICSERV) == 0)
            snprintf(peer, peer_size, strchr(host, ':') ? "[%s]:%s" : "%s:%s", host, port);
        net_tune(fd);
        return fd;
    }
    return -1;
}

/* A connection to the harness at `addr`, retried for 30 s (`forever`: until SIGTERM). */
int net_dial(const char *addr, int forever, volatile sig_atomic_t *stop) {
    struct addrinfo *ai = resolve(addr, 0);
    if (!ai) return -1;
    int fd = -1;
    for (int attempt = 0; (forever || attempt < 600) && fd < 0 && !*stop; attempt++) {
        fd = socket(ai->ai_family, ai->ai_socktype, ai->ai_protocol);
        if (fd >= 0 && connect(fd, ai->ai_addr, ai->ai_addrlen) != 0) {
            close(fd);
            fd = -1;
            struct timespec pause = {0, 50000000L};
            nanosleep(&pause, NULL);
        }
    }
    if (fd < 0 && !*stop) fprintf(stderr, "hil_target: cannot connect to %s: %s\n", addr, strerror(errno));
    freeaddrinfo(ai);
    if (fd >= 0) net_tune(fd);
    return fd;
}

