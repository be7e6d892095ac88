"""Recorded datasets in and out: `lsr data import` and `lsr data export`."""
