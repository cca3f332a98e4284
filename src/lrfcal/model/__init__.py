"""The rig model: everything the simulator, the calibration, ``plan`` and ``study`` share, pure (no I/O).

- :mod:`.kinematics`: the seed paper's eq. (3), the DH parameters and the mount pose, SO(3) helpers;
- :mod:`.chart`: the scan plane's pose in M', the DH chart and the regular one the solver moves it in, the
  canonical DH branch;
- :mod:`.unknowns`: the parameters the solver can estimate (the 10, the clock offset and the scanner's
  intrinsics), their order in the solver's vector, and the motor angle of a beam at a clock offset;
- :mod:`.rays`: each beam's origin and direction in W with their analytic Jacobian;
- :mod:`.observations`: the observation set, one interface for every kind of observation the estimate takes, and
  the marker model's constants as one object;
- :mod:`.marker`, :mod:`.sphere`: the marker observation model (ray-sphere with the beam's footprint) and its set;
- :mod:`.plane`: the surface observation model (ray-plane with the planes as nuisances) and its set.

See docs/architecture.md for where a new parameter or observation model goes.
"""
