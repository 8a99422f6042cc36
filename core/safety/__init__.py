"""The cell's safety decision, pure functions: the cell file, the robot's posed geometry and
silhouette, the separation of people from the robot, zones, and the state with its speed scale
(speed and separation monitoring and body-region limits after ISO/TS 15066). The service that
runs them live is `topseg.services.live.safety`. A monitoring aid, not a certified safety
device."""
