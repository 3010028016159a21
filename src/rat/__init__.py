"""rat: targeted behaviour attacks on deep reinforcement-learning agents (RAT, AAAI 2025)."""

__version__ = "0.1.0"
