"""``python -m ari_sfm.simulate SCENARIO OUT [--seed N] [--sigma S] [--image-scale X] [--images|--no-images]``.

Writes OUT/dataset/ and OUT/truth.json, like ``ari-sfm simulate SCENARIO -o OUT``.
"""
from __future__ import annotations

import argparse
import logging
import sys

from ari_sfm.simulate import SCENARIOS, ScenarioOverrides, simulate


def main(argv: list[str] | None = None) -> int:
    """Parse the arguments, simulate, print the two paths.

    Args:
        argv: The arguments (None: the process's).

    Returns:
        The exit code: 0 (a usage error exits 2 through argparse).
    """
    parser = argparse.ArgumentParser(prog="python -m ari_sfm.simulate", description=__doc__.splitlines()[0],
                                     epilog="scenarios: " + "; ".join(f"{k}: {v}" for k, v in SCENARIOS.items()))
    parser.add_argument("scenario", choices=list(SCENARIOS))
    parser.add_argument("out", help="output folder (OUT/dataset, OUT/truth.json)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sigma", type=float, default=0.05, help="pixel noise per coordinate (observations)")
    parser.add_argument("--image-scale", type=float, default=1.0, help="scale of image size and focal length")
    parser.add_argument("--images", action=argparse.BooleanOptionalAction, default=None,
                        help="render PNG images (default: per scenario)")
    parser.add_argument("--num-frames", type=int, default=None, help="calibration frames (scenario default)")
    parser.add_argument("--num-cameras", type=int, default=None, help="cameras (arc4, scale16)")
    parser.add_argument("-v", "--verbose", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(message)s")
    overrides = ScenarioOverrides(num_frames=args.num_frames, num_cameras=args.num_cameras)
    try:
        dataset_dir, truth_path = simulate(args.scenario, args.out, seed=args.seed, sigma_px=args.sigma,
                                           images=args.images, image_scale=args.image_scale, overrides=overrides)
    except ValueError as exc:
        parser.error(str(exc))
    sys.stdout.write(f"dataset: {dataset_dir}\ntruth:   {truth_path}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
