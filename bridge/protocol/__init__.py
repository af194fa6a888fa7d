"""Serial protocol codecs: pure, no I/O."""
