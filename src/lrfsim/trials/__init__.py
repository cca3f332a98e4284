"""Simulate, calibrate, compare with the truth: one trial (the unit of the recovery tests and studies), `lrfsim run`
(the closed loop on one scenario, with its files and tables), the comparison with the ground truth, and the
Monte-Carlo study (its variants, process pool and figures). The top room below the command line: imports every
room but testing."""
