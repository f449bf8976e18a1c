"""Contact and energy: the momentum observer, contact detection and its monitor, the power balance, the live kinetic energy."""
