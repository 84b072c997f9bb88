"""Edges of the testbed: messages (encode/decode) and transport (Zenoh config, key expressions)."""
