"""psonurbs: fit NURBS surfaces to 3D point clouds by particle swarm optimisation."""

__version__ = "0.1.0"
