"""Processes and batch jobs: the CLI, driver, worker, viewer, recorder, datagen, train, bench."""
