"""Reporting experiments: how success rates are counted and compared (:mod:`pipps.reporting.readings`)."""
