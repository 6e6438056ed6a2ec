"""Gradient studies on policy snapshots from real training runs (thesis §4.2, §4.4.1).

* :mod:`~pipps.studies.snapshot` — the policy and GP model of a trial, rebuilt from a result file;
* :mod:`~pipps.studies.gradients` — the landscape along a direction and the variance against
  the number of particles, with HDF5 output, rerun recordings and summary tables.
"""

from pipps.studies.snapshot import Snapshot, load_snapshot, pilco_direction

__all__ = ["Snapshot", "load_snapshot", "pilco_direction"]
