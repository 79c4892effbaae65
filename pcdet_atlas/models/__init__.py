"""Pure-torch detectors and their stages (no spconv, no compiled ops)."""
