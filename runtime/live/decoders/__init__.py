"""Sans-IO decoders: bytes in, timestamped joint samples (`Frame`) out; no sockets, never raise."""
