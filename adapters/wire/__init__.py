"""The wire: what a message is (``messages``), its bytes (``protocol``, the codec of
PROTOCOL.md), a byte stream cut into messages (``stream``), receipt stamps on a stream
socket (``receipt``) and the proof that a peer is the run's own target (``auth``).
Standard library and ``hil.common`` only; every transport and the SDK build on it."""
