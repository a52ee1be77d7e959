"""Test-only oracles: former implementations and diagnoses that read the truth, kept to check the package against."""
