"""Work beyond one process: local worker processes and Ray tasks, with retries (see
``docs/scaling.md``)."""
