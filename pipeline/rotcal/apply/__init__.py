"""Apply: a calibration put to use. ``apply_calibration`` corrects a
recording with a = P (R - O) (``rotcal apply``); ``export_calibration``
writes the calibration in the forms flight stacks and IMU tools load
(``rotcal export``). Both read ``calibration.json`` through
``model.calibration.Calibration``."""

from rotcal.apply.correct import correct, correction_covariance
from rotcal.apply.export import FORMATS, Export, export_calibration
from rotcal.apply.recording import Applied, apply_calibration, writable_file

__all__ = ["FORMATS", "Applied", "Export", "apply_calibration", "correct", "correction_covariance",
           "export_calibration", "writable_file"]
