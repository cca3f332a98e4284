"""Support for the tests and benchmarks, not used by any command: seeded random scenarios (broad random truths and
their labels). In the package, not under tests/, because the benchmarks import it too. Imports the rooms below
(scenario, world, simulation); no room imports it."""
