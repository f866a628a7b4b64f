"""Mechanics of the dome: deformed inner chamber surfaces for given target poses.

``geometric`` holds a kinematic stand-in (the dome pushed onto the target sphere and smoothly
blended), used until the hyperelastic FEM exists and kept as a fast baseline."""
