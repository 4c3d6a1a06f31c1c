"""Does a controller's fitness depend on its place in the batch, or on the number of CPU
devices? (`Task.evaluate` promises it does not; the README's "Fixed (2026-12-07): Bob on two
CPU devices" tells how it did, for sense-based Bob, while batches were sharded with
`shard_map`.)

One controller sampled from a config's task is copied into batches of several widths and
evaluated; each width prints the distinct fitnesses and the first place each occurs at:
one value per width, the same with one device and with two.

    python benchmarks/experiments/batch_place.py --devices 2   # Bob, two devices
    python benchmarks/experiments/batch_place.py --devices 1   # the same values
"""

import argparse
import dataclasses
from pathlib import Path

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "bob_walk.toml"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", type=Path, default=CONFIG)
    parser.add_argument("--devices", type=int, default=2, help="CPU devices JAX exposes")
    parser.add_argument("--duration", type=float, default=2.0, help="simulated seconds")
    parser.add_argument("--widths", default="1,16,40,64,500", help="batch widths, comma-separated")
    args = parser.parse_args()

    import jaxmotion as jm

    jm.use_cpu_cores(args.devices)
    import jax
    import jax.numpy as jnp
    import jax.random as jr
    import numpy as np

    from jaxmotion.experiment import load_config

    task = dataclasses.replace(load_config(args.config).task, duration=args.duration)
    one = jax.tree_util.tree_map(lambda a: a[0], task.sample(1, key=jr.key(0)))
    print(f"{args.config.name}, {args.duration} s, {len(jax.devices())} device(s)")
    for width in map(int, args.widths.split(",")):
        batch = jax.tree_util.tree_map(lambda a, w=width: jnp.repeat(a[None], w, axis=0), one)
        values, first = np.unique(np.asarray(task.evaluate(batch)), return_index=True)
        found = ", ".join(
            f"{float(v):.9g} from place {i}" for v, i in zip(values, first, strict=True)
        )
        print(f"width {width}: {found}")


if __name__ == "__main__":
    main()
