"""`python -m benchmark verify NAME`: an integrator or an effect checked against the plugin contract
(`benchmark.contract.verify`).
"""

from __future__ import annotations


from reelbench.benchmark.cli import common
from reelbench.benchmark.core.options import UsageError


def cmd_verify(args) -> int:
    """The plugin contract (`benchmark.contract.verify`): exit 0 when every check holds, 1 otherwise."""
    from reelbench.benchmark.contract import verify

    ov = common.overrides(args.set)
    for name in args.names:  # an unknown name, a scene without the effect or a bad one: exit 2 before any work
        kind = verify.kind_of(name)
        if kind == "integrator" and (args.scene or ov):
            raise UsageError(f"--scenes/--set are for an effect; {name} is an integrator, checked on its own "
                             "small scenes")
        if kind == "effect":
            verify.effect_scene(name, args.scene, ov)
    return max(verify.verify(name, scene=args.scene, overrides=ov, log=print) for name in args.names)


def add_verify(sub) -> None:
    v = sub("verify", "check an integrator or an effect (a plugin's, or one of the project's) against the plugin "
                      "contract: one line per check with its figure; exit 1 on a failure",
            "Check an integrator or an effect against the plugin contract (benchmark/contract/integrator.py and "
            "effect.py): for an integrator its declared order on a fixed-length and a reeling scene, its statuses and "
            "guards, its capabilities, determinism and its flop count; for an effect its gradients against autodiff, "
            "its power, the energy balance with a reference method and the validation of its scene keys. Small "
            "scenes: seconds to tens of seconds, mostly compilation.")
    v.add_argument("names", nargs="+", metavar="NAME", help="registered integrators or effects (see `list`)")
    common.add_scenes(v, "for an effect: a scene that lists it (default: a small scene with the effect and what it "
                         "needs; required when its keys have no default)", one=True)
    common.add_set(v, "for an effect: a scene override, repeatable, e.g. --set stiffness=20")
    v.set_defaults(func=cmd_verify)
