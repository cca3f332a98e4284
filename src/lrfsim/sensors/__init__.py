"""The instruments: the laser scanner's model (timing, beam poses, footprint, mixed pixel, noise, echoes), the
servo's trajectory and joint states, and the person with the tape. Each reads its section of the scenario; none
knows the scene it measures (the ray cast is lrfsim.cast). Imports the scenario room only."""
