"""Scene synthesis: the density function over scenes, the posed humanoid and furniture, and the
renderer that turns a scene into top-view depth with exact labels and sensor noise."""
