"""rascal: the runtime every module stands on (`rascal.runtime`: the bus, shared time, the module
lifecycle, configuration) and, around it, the tools: the `rascal` command, the supervisor, the
recorder, the report and the live view."""
