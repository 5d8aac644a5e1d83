"""The recursive estimator: warm-started fits of each injection filtered per injector (Kalman), its
state, and the per-injector bank the daemon and the replay drive."""
