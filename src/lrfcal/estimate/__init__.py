"""The one estimate: the least-squares engine, its covariance, what the data determine, the checks."""
