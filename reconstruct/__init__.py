"""Reflectance models, coordinates, rendering, geometry and the reconstruction methods. Pure."""
