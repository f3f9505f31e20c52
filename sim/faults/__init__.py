"""Hostile and broken input against the whole service: the fault suite (``make faults``) and the
settings-file fuzzer. The top layer of all: it may import every other ``sim`` folder and all of
``mavvo``, its command line included (it checks settings files through it, as an operator would)."""
