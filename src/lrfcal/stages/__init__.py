"""The stages of the calibration, one module each (see lrfcal.pipeline)."""
