"""The Zenoh wire: the loop's messages (encode/decode, the protocol version) and the transport (session config,
credentials, access rules, key expressions)."""
