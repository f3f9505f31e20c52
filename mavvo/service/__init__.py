"""The service: MAVLink link, clocks and attitude pairing, camera sources, outgoing messages,
recorder, settings and YAML loading, systemd notifications and the daemon that wires them. May import
every lower layer (``odometry``, ``estimation``, ``geometry``); never ``mavvo.commands`` or ``sim``."""
