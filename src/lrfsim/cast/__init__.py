"""The ray cast with MuJoCo's mj_multiRay: the rays of a chunk of scans and their casts, the chunks over threads
with the mixed-pixel model, and a forked helper process for casts that hold the GIL. Imports the scenario and
sensors rooms (the scene comes in as an argument)."""
