"""Hostile and broken input against the whole service: the fault suite (``make faults``) and the
settings-file fuzzer. Outside the package and above all of it: it drives ``mavvo``'s command line as an
operator would."""
