"""Reading and writing files, nothing else: recordings in, calibrations out, and the one atomic writer every file and
folder of the programs uses. Below the method (docs/architecture.md): io imports the data types, the model, the
result and the errors, never the estimate, the stages, the orchestrator, the report or the commands.

* reading a recording: :mod:`.recording` (the folder: bag or scan log, tape distances, rig file), :mod:`.bag`
  (ROS bags; :mod:`.bag_messages`, :mod:`.bag_scans` and :mod:`.bag_servo` its parts; :mod:`.bag_raw`,
  :mod:`.bag_arrays` and :mod:`.wire` read LaserScan and JointState in bulk, :mod:`.multiecho` MultiEchoLaserScan),
  :mod:`.scanlog` (text logs), :mod:`.yamlfile` (any YAML file a user gives);
* writing a ROS 2 bag in bulk: :mod:`.mcap_write` (the MCAP file rosbags' Writer writes, from messages as arrays;
  the simulator's bag);
* writing a calibration's files: :mod:`.calibration_yaml`, :mod:`.urdf`, :mod:`.ros_launch` and :mod:`.ply`
  (the output folder that holds them with report.md: lrfcal.commands.calibration_folder); :mod:`.truth` aligns a
  simulator's ground truth to the calibration for the report, lrfcal.commands.calibrate and lrfsim;
* the rig file: :mod:`.rig` (its sections' models are lrfcal.types.sources');
* :mod:`.files`: the one atomic writer (files and folders renamed into place when complete), the manifest of an
  output folder and the checks of output paths.

Nothing is imported here: each module is imported by its own name.
"""
