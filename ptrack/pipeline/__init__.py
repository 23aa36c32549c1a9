"""The run: config loading, keyframe files, `ptrack run` / `evaluate` / `compare`, and the metrics they
report. The only layer that picks an estimator by name; imports every layer below."""
