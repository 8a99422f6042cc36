"""Live services: what runs on a cell PC (driver, worker, viewer, bridge, recorder, status,
router, calibration and device listing)."""
