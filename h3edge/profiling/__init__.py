"""Timing and profile documents: per-component timings and their log (:mod:`.timing`), and the
profile document a run or a service gives, with its report (:mod:`.report`)."""
