"""Problem-definition scripts: one importable factory per scene (see stircasadi.problem)."""
