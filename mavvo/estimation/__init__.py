"""Robust estimation: relative pose with known gravity (RANSAC, local optimisation, refinement, model
selection). Imports ``mavvo.geometry`` and the top-level vocabulary only."""
