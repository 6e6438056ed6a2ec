"""Build the pipps API reference from the docstrings with pdoc; exit 1 on any pdoc warning.

    python docs/api/build.py                 # writes build/api/index.html (build/ is git-ignored)
    python docs/api/build.py --out DIR       # anywhere else

The public modules are listed in ``PUBLIC`` below and explained in docs/api/index.md, the
landing page of the reference. The build imports pipps on the CPU (``JAX_PLATFORMS=cpu`` unless
set) and needs the ``docs`` extra: ``pip install -e ".[docs]"``.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import time
import warnings
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent

#: the modules whose pages make up the reference, in the order of the landing page
PUBLIC = (
    "pipps",
    "pipps.tasks",
    "pipps.costs",
    "pipps.gaussian",
    "pipps.policies",
    "pipps.rollout",
    "pipps.gp",
    "pipps.particles",
    "pipps.particles.simulator",
    "pipps.propagation",
    "pipps.optimizers",
    "pipps.pilco",
    "pipps.experiments",
    "pipps.reporting",
    "pipps.studies",
    "pipps.studies.contact",
    "pipps.studies.contact_studies",
    "pipps.systems",
    "pipps.systems.linear_actions",
    "pipps.systems.contact",
)


def _work_around_pdoc(modules) -> None:
    """Make two valid Python constructs visible to pdoc, in this process only.

    * Names a package loads lazily through a module-level ``__getattr__`` (PEP 562; ``pipps.tasks``
      loads ``ENV_IDS`` and ``PippsEnv`` so that importing it does not import gymnasium): pdoc
      reads ``__all__`` names from the module's ``__dict__`` only, so they are loaded here.
    * ``typing.NamedTuple`` classes in modules with postponed annotations: the generated
      ``__new__`` claims a module that does not exist, so pdoc cannot resolve its annotations
      (an open pdoc bug, mitmproxy/pdoc#765). It is given its class's module.
    A name that does not resolve at all is left alone, and pdoc's warning fails the build.
    """
    import importlib

    for name in modules:
        mod = importlib.import_module(name)
        for attr in getattr(mod, "__all__", ()):
            if attr not in mod.__dict__:
                try:
                    setattr(mod, attr, getattr(mod, attr))
                except AttributeError:
                    pass
    for name, mod in list(sys.modules.items()):
        if name != "pipps" and not name.startswith("pipps."):
            continue
        for obj in list(vars(mod).values()):
            new = getattr(obj, "__new__", None)
            if (
                isinstance(obj, type)
                and issubclass(obj, tuple)
                and hasattr(obj, "_fields")
                and getattr(new, "__module__", "").startswith("namedtuple_")
            ):
                new.__module__ = obj.__module__


def _link_names(markdown: str) -> str:
    """The landing page's `pipps.x` and `pipps.x.name()` in backticks, linked to their pages."""

    def link(m: re.Match) -> str:
        parts = m[1].split(".")
        for cut in range(len(parts), 0, -1):
            module = ".".join(parts[:cut])
            if module in PUBLIC:
                anchor = ".".join(parts[cut:])
                exported = getattr(sys.modules[module], "__all__", None)
                if anchor and (exported is None or parts[cut] not in exported):
                    return m[0]  # not a documented name: no link
                href = module.replace(".", "/") + ".html" + (f"#{anchor}" if anchor else "")
                return f"[{m[0]}]({href})"
        return m[0]

    return re.sub(r"`(pipps(?:\.\w+)*)(?:\(\))?`", link, markdown)


def build(out: Path) -> list[str]:
    """Render the reference into ``out``; return pdoc's warnings (empty: a clean build)."""
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    import pdoc
    import pdoc.render

    pdoc_dir = str(Path(pdoc.__file__).resolve().parent)
    problems: list[str] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _work_around_pdoc(PUBLIC)
        pdoc.render.configure(
            docformat="google",  # Google sections (Args:, Returns:) and reST roles, as the docstrings use
            template_directory=HERE / "templates",
            footer_text=f"pipps {__import__('pipps').__version__}",
            search=True,
            show_source=True,
        )
        pdoc.render.env.globals["landing_markdown"] = _link_names((HERE / "index.md").read_text(encoding="utf-8"))
        pdoc.pdoc(*PUBLIC, output_directory=out)
    for w in caught:
        if str(Path(w.filename).resolve()).startswith(pdoc_dir):
            problems.append(f"{w.category.__name__}: {w.message}")
    return problems


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "build" / "api", help="output folder (default: build/api)")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    problems = build(args.out)
    for p in problems:
        print(f"pdoc warning: {p}", file=sys.stderr)
    if problems:
        print(f"API reference: {len(problems)} warning(s), failing", file=sys.stderr)
        return 1
    print(f"API reference: {args.out / 'index.html'} ({time.perf_counter() - start:.1f} s, no warnings)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
