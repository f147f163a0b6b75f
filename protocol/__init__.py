"""The rascal wire protocol: messages, sans-IO codec and framing, and the transport."""
