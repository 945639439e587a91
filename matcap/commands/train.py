"""`matcap train`: train an SDM-UniPS network on `matcap synth` data (see networks.train)."""
from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser(
        "train",
        help="train the normal or BRDF network on synthetic data (resumable; torchrun for data-parallel)",
        description="Train an SDM-UniPS network. Data-parallel: torchrun --nproc_per_node=2 -m networks.train ...",
    )
    from networks.trainconfig import add_arguments

    add_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from networks.train import config_from_args, train

    result = train(config_from_args(args), resume=args.resume, init=args.init, progress=not args.quiet,
                   overwrite=args.overwrite)
    if result.get("stopped"):
        print(f"stopped at step {result['step']} (checkpoint saved): continue with the same command and --resume")
        return 130
    print(f"done: step {result['step']}, best validation {result['best']:.4g}")
    return 0
