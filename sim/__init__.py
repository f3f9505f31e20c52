"""The world outside the companion computer: synthetic scenes, and later the rendered camera, the
simulated flight controller and trajectory evaluation. Depends on mavvo; mavvo never imports it."""
