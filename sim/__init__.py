"""MPM ranks: physics kernels (numba), scenes, MPI decomposition, publishing."""
