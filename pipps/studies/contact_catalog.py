"""The contact studies' names, settings and measured run times, without importing JAX (the CLI's
help lists them; :mod:`pipps.studies.contact_studies` runs them)."""

from __future__ import annotations

STUDIES = ("heaviside", "relaxed", "fig1", "ball", "pushing", "scaling")

#: per study, (quick, full) settings
SETTINGS = {
    "heaviside": (dict(thetas=9, samples=100, replicates=100), dict(thetas=25, samples=100, replicates=1000)),
    "relaxed": (dict(nus=(1.0, 0.1, 0.01), samples=(2, 10, 100, 1000), replicates=100),
                dict(nus=(1.0, 0.3, 0.1, 0.03, 0.01, 0.003, 0.001), samples=(2, 4, 10, 30, 100, 300, 1000), replicates=1000)),
    "fig1": (dict(thetas=11, samples=100, replicates=50, iterations=30, descents=2),
             dict(thetas=31, samples=100, replicates=400, iterations=100, descents=10)),
    "ball": (dict(thetas=5, samples=16, replicates=8, timeconsts=(0.02,), reference=16),
             dict(thetas=11, samples=32, replicates=32, timeconsts=(0.04, 0.02, 0.01), reference=128)),
    "pushing": (dict(stiffness=(10.0, 1e3, 3e4), kappas=(10.0, 1e3), samples=32, replicates=32),
                dict(stiffness=(10.0, 31.6, 100.0, 316.0, 1e3, 3.16e3, 1e4, 3.16e4, 1e5), kappas=(1.0, 10.0, 100.0, 1e3, 1e4),
                     samples=32, replicates=256)),
    "scaling": (dict(stiffness=(10.0, 1e3), iterations=20, samples=16, seeds=2, policy_iterations=20),
                dict(stiffness=(10.0, 100.0, 1e3, 1e4), iterations=150, samples=32, seeds=5, policy_iterations=150)),
}
ALPHA = 1e-3  # family-wise false-alarm probability of each test of unbiasedness

#: minutes each study took here (one core shared with an experiment; docs/contact.md), quick and full
MINUTES = {"heaviside": (0.5, 4.0), "relaxed": (1.5, 25.0), "fig1": (3.0, 40.0), "ball": (12.0, 60.0),
           "pushing": (2.0, 20.0), "scaling": (3.0, 40.0)}


def estimated_minutes() -> dict:
    """Per study, (quick, full) minutes as measured for docs/contact.md: shown before a study starts."""
    return dict(MINUTES)


def settings_of(study: str, full: bool, **overrides) -> dict:
    if study not in SETTINGS:
        raise ValueError(f"unknown contact study {study!r}; choose one of {STUDIES}")
    out = dict(SETTINGS[study][1 if full else 0])
    unknown = set(overrides) - set(out)
    if unknown:
        raise ValueError(f"{study}: unknown settings {sorted(unknown)}; it takes {sorted(out)}")
    return {**out, **overrides}


