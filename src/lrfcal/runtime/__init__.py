"""How the programs run: the BLAS thread policy, the memory policy and tasks on every core."""
