"""The core every stage stands on: camera models and their fit, attitude, the star catalog, sky geometry, errors.

Imports nothing else from skyview."""
