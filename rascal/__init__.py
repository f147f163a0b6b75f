"""rascal runtime: the bus, shared time, the module lifecycle and the `rascal` command."""
