"""Back-analysis: calibrate a scenario's parameters to an observed event (issue 28).

A stage above :mod:`avflow.ensemble` (it runs its model runs as ensemble members); nothing
below imports it. :func:`calibrate` is ``avflow calibrate CALIB.yaml -o OUTDIR``.
"""

from avflow.calibration.run import CalibrationResult, calibrate
from avflow.calibration.spec import CalibrationError, load_calibration, parse_calibration

__all__ = ["calibrate", "CalibrationResult", "CalibrationError", "load_calibration",
           "parse_calibration"]
