"""Browser view of the twin (viser)."""
