"""The pure core, never importing rclpy, in five rooms: ``robot`` (the model, its limits,
settings and dynamics), ``check`` (the feasibility check of a trajectory and its constraint
kinds), ``live`` (the live monitor of joint states), ``contacts`` (the observer, contact
detection and the power balance) and ``compiled`` (the Numba kernels)."""
