"""The commands' use cases, above the method: each reads what a command is given, runs the method and writes what
it makes, without command-line code (lrfcal.cli parses and prints; lrfsim runs calibrate_folder too).

* :mod:`.calibrate`: calibrate a recording folder and write the results (``lrfcal calibrate``, ``lrfsim run``):
  its inputs read and checked, then (:mod:`.calibration_run`, imported only then, with the method) calibrated, the
  figures drawn meanwhile, and written into :mod:`.calibration_folder` (calibration.yaml, rig.urdf, the ROS 2 files,
  the clouds, report.md and the figures, renamed into place when complete);
* :mod:`.inspect_bag` and :mod:`.inspect_log`: what a bag or a scan log holds, the rig file that reads it and the
  DH proposed from it (``lrfcal inspect``);
* :mod:`.reproject`: every beam into frame M (``lrfcal reproject``);
* :mod:`.convert`: a scan log as a ROS 2 bag (``lrfcal convert``).

Nothing is imported here: each module is imported by its own name.
"""
