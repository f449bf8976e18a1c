"""The compiled (Numba) kernels the check, the frames, the force laws and the observer run on."""
