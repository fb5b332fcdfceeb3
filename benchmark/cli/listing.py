"""`python -m benchmark list`: the registered integrators and effects and the shipped scenes.
"""

from __future__ import annotations


def cmd_list(args) -> int:
    from reelbench.benchmark.runs.sweep import EXTENDED_METHODS
    from reelbench.integrators import available, get_integrator, origin, plugin_errors
    from reelbench.models import available_scenes

    print("scenes:", ", ".join(available_scenes()))
    names, failed_methods = available(), plugin_errors()
    width = max(map(len, [*names, *failed_methods]), default=10)  # one column of names, however long
    for name in names:
        integ = get_integrator(name)
        caps = ", ".join(sorted(c.value for c in integ.capabilities))
        own = origin(name).own
        # a plugin is a guest: it joins no sweep unasked
        sweep = ("extended" if name in EXTENDED_METHODS else "default") if own else "plugins"
        guest = "" if own else f"  ({origin(name).label()})"
        print(f"  {name:{width}s}  order {integ.order}  {sweep:10s}  [{caps}]  {integ.description}{guest}")
    for name, err in failed_methods.items():
        print(f"  {name:{width}s}  FAILED TO LOAD: {err}")
    print("  (default: in the default sweep; extended: only in the extended sweep, or when --integrators names it; "
          "plugins: a plugin, swept with --with-plugins or when --integrators names it)")
    from reelbench.models import EFFECTS
    from reelbench.models.effects import effect_origin, plugin_errors as effect_plugin_errors

    failed = effect_plugin_errors()  # loads the reelbench.effects plugins first
    print("effects:", ", ".join(n if effect_origin(n).own else f"{n} ({effect_origin(n).label()})" for n in EFFECTS))
    for name, err in failed.items():
        print(f"  {name:{max(map(len, failed))}s}  FAILED TO LOAD: {err}")
    return 0


def add_list(sub) -> None:
    sub("list", "registered integrators and shipped scenes").set_defaults(func=cmd_list)
