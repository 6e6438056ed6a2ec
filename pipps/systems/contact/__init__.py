"""Known simulators with contact, for first-, zeroth- and α-order gradients (Suh et al. 2022; docs/contact.md).

Each module is one family of the source documents' examples, returned as a
:class:`~pipps.systems.contact.base.ContactExample` (problem, simulator, decision variables, action
noise and, where it is known, the exact smoothed gradient):

* :mod:`~pipps.systems.contact.heaviside` — the Heaviside and its relaxation (closed form);
* :mod:`~pipps.systems.contact.fig1` — the drop, the throw against an inelastic wall, the pivoting bar;
* :mod:`~pipps.systems.contact.pushing` — 1-D pushing with a penalty spring, implicit time-stepping and a
  log-barrier, and the point mass against a wall (Fig. 6);
* :mod:`~pipps.systems.contact.mjx_scenes` — the ball against a wall and a dome in MuJoCo MJX (loaded
  on use: it imports MuJoCo).
"""

from pipps.systems.contact import base, fig1, heaviside, pushing
from pipps.systems.contact.base import ContactExample, one_step_problem, smoothed

__all__ = ["ContactExample", "base", "fig1", "heaviside", "one_step_problem", "pushing", "smoothed"]
