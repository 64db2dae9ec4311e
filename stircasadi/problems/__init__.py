"""The problem scripts shipped with stircasadi: one scene per module (``stircasadi problems``
lists them; ``stircasadi.problem.load_problem`` imports them by name or path)."""
