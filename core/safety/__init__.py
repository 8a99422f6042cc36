"""The cell's safety decision, pure functions: the cell file, the robot's posed geometry and
silhouette, the separation of people from the robot, zones, and the state with its speed scale
(speed and separation monitoring and body-region limits after ISO/TS 15066). The service that
runs them live is `topseg.services.live.safety`. A monitoring aid, not a certified safety
device."""

#: The worker that feeds the safety decision labels without the model's precision stages, its
#: context prior and its two checks (`--context-prior off --person-check off`): they take
#: phantom people off robots and objects, and now and then a real person with them. A phantom
#: person is a false stop; a missed one a missed stop. Chosen on the validation sequences
#: (states equal: all on 98.5 %, the prior off 98.8 %, all off 99.0 %; never `clear` when the
#: truth said `stop` with any); on the held-out ones the prior read a person whole as an
#: object in 4 frames that said `clear` where the truth said `stop`, and the checks without it
#: one (docs/results.md).
PRECISION_STAGES = "off"
#: the worker's options that say so
WORKER_OPTIONS = ("--context-prior", PRECISION_STAGES, "--person-check", PRECISION_STAGES)
