"""What the three services agree on: messages, codec, keys, Zenoh config, clocks."""
