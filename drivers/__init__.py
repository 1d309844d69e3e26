"""Device drivers and the simulated rig.  Knows nothing of ``station``."""
