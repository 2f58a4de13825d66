"""cegc-train: train CEGC on synthetic pairs; resumable, checkpoints every few minutes.

    cegc-train --config params/train_7scenes.yaml [--resume runs/7scenes/last.pt]
    torchrun --nproc_per_node=4 -m cegc_ros.tools.train --config ...   # DistributedDataParallel
"""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="cegc-train", description=__doc__.splitlines()[0])
    ap.add_argument("--config", required=True, help="training YAML (sections model, loss, data, train)")
    ap.add_argument("--resume", default=None, help="a last.pt written by an earlier run")
    ap.add_argument("--device", default="auto", help="auto | cpu | cuda[:N]")
    ap.add_argument("--max-minutes", type=float, default=None, help="override train.max_minutes")
    ap.add_argument("--out-dir", default=None, help="override train.out_dir")
    args = ap.parse_args(argv)
    from cegc_ros.data.pair_cache import PairCacheError
    try:
        from cegc_ros.training import Config, Trainer
        cfg = Config.from_yaml(args.config)
        if args.max_minutes is not None:
            cfg.train.max_minutes = args.max_minutes
        if args.out_dir is not None:
            cfg.train.out_dir = args.out_dir
        trainer = Trainer(cfg, resume=args.resume, device=args.device)
    except (OSError, ValueError, TypeError, KeyError) as err:
        print(f"cegc-train: {err}".splitlines()[0], file=sys.stderr)
        return 2
    except PairCacheError as err:
        # before any training or rendering: the config's data.pair_cache / val_pair_cache
        print(f"cegc-train: {str(err).splitlines()[0]} (the config's data.pair_cache or "
              f"data.val_pair_cache; make it with cegc-make-pairs, docs/data.md)", file=sys.stderr)
        return 2
    val = trainer.run()
    print(f"cegc-train: step {trainer.step}, {trainer.elapsed / 60:.1f} min, last validation {val}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
