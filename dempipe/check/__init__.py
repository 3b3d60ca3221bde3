"""Predictions without simulating: stable steps, soft contacts, overlaps, memory and run size."""
