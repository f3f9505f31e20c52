"""Camera calibration for ``mavvo calibrate``: calibration boards and their detection
(:mod:`~mavvo.calibration.boards`), view selection and the solve (:mod:`~mavvo.calibration.solve`),
and other tools' calibration files (:mod:`~mavvo.calibration.formats`). Above the service layer: it
may import everything below it; only the command line imports it."""
