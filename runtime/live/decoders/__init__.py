"""Sans-IO decoders: bytes in, timestamped joint samples (`SourceFrame`) out; no sockets, never raise."""
