"""`lrfsim plan`: the predicted 1-sigma of every calibrated parameter of a scenario without calibrating, from a
sparse noise-free cast of the scans that can see a marker. Imports the rooms below (scenario to simulation)."""
