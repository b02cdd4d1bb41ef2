"""Remote inference: the wire codec (and, with Zenoh, the policy server and client)."""
