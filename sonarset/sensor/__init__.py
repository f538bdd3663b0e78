"""The eRTIS imaging chain shared by the simulator and the raw importer: the sensor's physics
(``ertis``), the beamformers (``beamform``, the fast path; ``exact``) and the energyscape
post-processing (``energyscape``). It imports neither ``sonarset.sim`` nor ``sonarset.ingest``."""
