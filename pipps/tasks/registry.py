"""Finding a task's record (:class:`~pipps.tasks.spec.TaskSpec`) by name, by path, or by entry point.

:func:`get_task` resolves what a configuration, a result file or the command line names:

1. a :class:`TaskSpec` itself: registered under its name in this process (later lookups by name
   find it);
2. ``"module:attribute"``: the module is imported and the attribute is a record, or a function of
   no arguments that returns one (``pipps run --task mypkg.tasks:pendulum``);
3. a name: the built-in tasks (:data:`pipps.tasks.builtin.BUILTIN`), then those registered in this
   process (:func:`register`), then the ``source`` a configuration stores, then the entry points
   of the ``pipps.tasks`` group of installed packages::

       # a package's pyproject.toml
       [project.entry-points."pipps.tasks"]
       pendulum = "mypkg.tasks:pendulum"

**Where a task came from.** Every task but the built-in ones is known with its *source*, the
``module:attribute`` it was loaded from (an entry point's value, or the function :func:`register`
was given, when that is importable), or None for a record registered as an object. An
experiment's configuration stores it (``task_source``), so a result file says where its task came
from, and resuming or tabulating it in another process imports it from there. A task that cannot
be found raises :class:`TaskUnavailable`, one line that names the task, where it was looked for
and what to do.
"""

from __future__ import annotations

import importlib
import importlib.metadata
from typing import Callable

from pipps.tasks.spec import TaskSpec

#: The entry-point group an installed package declares its tasks in.
ENTRY_POINT_GROUP = "pipps.tasks"


class TaskUnavailable(ValueError):
    """A task cannot be found or loaded; the message says which, where it was looked for, and what to do."""


#: records registered in this process: name -> (record, source or None)
_REGISTERED: dict[str, tuple[TaskSpec, str | None]] = {}


def _builtin() -> dict[str, TaskSpec]:
    from pipps.tasks.builtin import BUILTIN

    return BUILTIN


def register(task: TaskSpec | str, factory: Callable[[], TaskSpec] | None = None, *,
             source: str | None = None) -> TaskSpec:
    """Make a task findable by name in this process: ``register(spec)``, or ``register(name,
    factory)`` with a function of no arguments that returns the record (called now; its name must
    be ``name``). Registering a name again replaces the record (a notebook cell run twice); a
    built-in task's name cannot be taken. Returns the record.

    ``source``: the ``module:attribute`` it can be imported from in another process; default the
    factory's own path when it has one (a function at a module's top level, not ``__main__``)."""
    if isinstance(task, TaskSpec):
        if factory is not None:
            raise TypeError("register(spec) or register(name, factory), not both")
        spec, name = task, task.name
    else:
        if not isinstance(task, str) or not callable(factory):
            raise TypeError("register(spec) or register(name, factory) with a function that returns a TaskSpec")
        name = task
        spec = _as_spec(factory(), f"the factory registered as {name!r}")
        if spec.name != name:
            raise ValueError(f"register({name!r}, …): the factory returns the task {spec.name!r}")
        source = source or _path_of(factory)
    if spec.name in _builtin():
        raise ValueError(f"{spec.name!r} is a built-in task; give yours another name (TaskSpec(..., name=…))")
    _REGISTERED[spec.name] = (spec, source)
    return spec


def unregister(name: str) -> None:
    """Forget a task registered in this process (tests; a name taken by mistake)."""
    _REGISTERED.pop(name, None)


def get_task(ref: TaskSpec | str, *, source: str | None = None) -> TaskSpec:
    """The record ``ref`` names (module docstring). ``source``: where a stored configuration says the
    task came from, imported when the name is not known here.

    Raises:
      TaskUnavailable: no such task, or its source cannot be imported or is no task.
    """
    if isinstance(ref, TaskSpec):
        if _builtin().get(ref.name) is ref:
            return ref
        if ref.name in _builtin():
            raise TaskUnavailable(f"{ref.name!r} is a built-in task; give yours another name (TaskSpec(..., name=…))")
        known = _REGISTERED.get(ref.name)
        if known is None or known[0] is not ref:
            register(ref)
        return ref
    if not isinstance(ref, str) or not ref:
        raise TaskUnavailable(f"a task is a name, MODULE:ATTRIBUTE or a TaskSpec, got {ref!r}")
    if ":" in ref:
        return load(ref)
    if ref in _builtin():
        return _builtin()[ref]
    if ref in _REGISTERED:
        return _REGISTERED[ref][0]
    if source is not None:
        try:
            spec = load(source)
        except TaskUnavailable as err:
            raise TaskUnavailable(f"task {ref!r}: its source {source} cannot be loaded here ({err}); make it "
                                  "importable (install its package, or run from its folder), or name where it is now "
                                  "with --task MODULE:ATTRIBUTE") from None
        if spec.name != ref:
            raise TaskUnavailable(f"task {ref!r}: its source {source} now holds the task {spec.name!r}")
        return spec
    entry = _entry_point(ref)
    if entry is not None:
        return load(entry.value, what=f"the entry point {ref!r} ({entry.value})")
    raise TaskUnavailable(f"unknown task {ref!r}; choose one of {', '.join(task_names())}, a task registered with "
                          "pipps.tasks.register, or MODULE:ATTRIBUTE of a task of your own")


def task_source(name: str) -> str | None:
    """Where the task registered as ``name`` came from (module docstring); None for a built-in task
    and for a record registered as an object."""
    known = _REGISTERED.get(name)
    return None if known is None else known[1]


def task_names() -> list[str]:
    """The tasks findable by name here: built-in, registered, and declared by entry points (not loaded)."""
    names = list(_builtin()) + [n for n in _REGISTERED if n not in _builtin()]
    return names + sorted(e.name for e in _entry_points() if e.name not in names)


def load(path: str, *, what: str | None = None) -> TaskSpec:
    """The task at ``"module:attribute"`` (a record, or a function of no arguments returning one),
    registered under its name with ``path`` as its source. Loading a path again returns the record
    registered from it.

    Raises:
      TaskUnavailable: the path is malformed, its module cannot be imported, or it holds no task.
    """
    what = what or path
    module_name, sep, attribute = path.partition(":")
    if not sep or not module_name or not attribute or ":" in attribute:
        raise TaskUnavailable(f"{path!r} is not MODULE:ATTRIBUTE (e.g. mypkg.tasks:pendulum)")
    for spec, source in _REGISTERED.values():
        if source == path:
            return spec
    try:
        module = importlib.import_module(module_name)
    except Exception as err:  # noqa: BLE001 - whatever the user's module raises, say it in one line
        raise TaskUnavailable(f"{what}: cannot import {module_name} ({type(err).__name__}: {err})") from None
    obj = module
    for part in attribute.split("."):
        if not hasattr(obj, part):
            raise TaskUnavailable(f"{what}: {module_name} has no attribute {attribute!r}")
        obj = getattr(obj, part)
    if not isinstance(obj, TaskSpec) and callable(obj):
        try:
            obj = obj()
        except Exception as err:  # noqa: BLE001
            raise TaskUnavailable(f"{what}: calling {attribute}() failed ({type(err).__name__}: {err})") from None
    spec = _as_spec(obj, what)
    if spec.name in _builtin():
        raise TaskUnavailable(f"{what}: its task is named {spec.name!r}, a built-in task's name")
    _REGISTERED[spec.name] = (spec, path)
    return spec


def _as_spec(obj, what: str) -> TaskSpec:
    if not isinstance(obj, TaskSpec):
        raise TaskUnavailable(f"{what} is a {type(obj).__name__}, not a pipps.tasks.TaskSpec")
    return obj


def _path_of(fn) -> str | None:
    """``module:qualname`` of a function importable by it, else None."""
    module, qualname = getattr(fn, "__module__", None), getattr(fn, "__qualname__", "")
    if not module or module == "__main__" or not qualname or "<" in qualname:
        return None
    return f"{module}:{qualname}"


def _entry_points():
    return importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)


def _entry_point(name: str):
    found = [e for e in _entry_points() if e.name == name]
    return found[0] if found else None
