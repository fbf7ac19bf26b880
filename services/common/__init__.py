"""Shared runtime: config, flags, codec, session, service base, logging."""
