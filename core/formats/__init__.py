"""File and wire formats: Zenoh messages, MCAP recordings, the Zarr dataset."""
