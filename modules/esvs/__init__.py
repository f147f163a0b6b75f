"""ESVS: the stereo vision system (simulated cameras, vision pipeline, real-time round, watchdog)."""
