"""What the laser sees: the scene's solids and markers in W from the scenario alone, the checks of that geometry,
the MuJoCo model of rig and scene compiled from it, and what a sweep or spin can see (geometry only). Imports the
scenario and sensors rooms."""
