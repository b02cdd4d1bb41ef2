"""openral over Zenoh: the transport (settings, sessions and requests, keys, the wire codec), then the services on it.

The policy server, its client and the ``remote_policy`` skill are such services. Nothing is
imported here: the modules that need Zenoh (the ``remote`` extra) load it themselves.
"""
