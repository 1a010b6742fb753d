"""Capture: sessions that drive a camera through a plan (verified, hashed frames in a manifest,
a streamed merge), jobs (TOML) end to end, run folders and schedules."""
