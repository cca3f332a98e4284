"""One simulated recording: the simulation as arrays (cast once, noise drawn per seed), its result, the faults
injected into it, and the recording folder written from it (lrfsim.simulation.recording; simulate and write in one
call: lrfsim.simulation.to_folder). Imports the rooms below: scenario, sensors, world, cast."""
