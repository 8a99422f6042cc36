"""Pure computation: labels, camera, scenes, features, forest, CRF, metrics, wire format."""
