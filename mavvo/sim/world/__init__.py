"""The simulated world: textured scene, OpenCV renderer, trajectories with exact truth, synthetic
two-view scenes, the simulation clock, injected faults and the rendered camera."""
