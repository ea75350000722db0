"""How 3D-body identification answers right and wrong clicks, on rendered tank images.

    python benchmarks/bench_body_clicks.py [--sets 80] [--seed 11]

Six rendered views of test_cavity's body (``ari_sfm.simulate.body_images``: cameras 450-650 mm away, up to
150 mm aside, rolled up to 5 deg, behind a 6 mm wall into water; particles, a wall streak, glare, a faint
reflection) and random sets of 4 clicked points spread over the body (``click_spread`` >= 0.5: smaller
spreads are refused), each click 0-3 px off its dot. Every second set has one id replaced by its body
neighbour's (the commonest clicking mistake: the next dot). Prints per kind the outcomes: identified with
every id right, identified with some id wrong, refused (ClickError), and the seconds per image.
"""
from __future__ import annotations

import argparse
import time
from collections import Counter

import numpy as np

from ari_sfm.body import ClickError, find_body
from ari_sfm.body.identify import click_spread
from ari_sfm.simulate.body_images import cavity_body, cavity_view, render_body_image


def main(sets: int, seed: int) -> None:
    body = cavity_body()
    ids, xyz = body.points_3d()
    rng = np.random.default_rng(seed)
    images = []
    for k in range(6):
        view = cavity_view(roll_deg=rng.uniform(-5, 5), centre_mm=(rng.uniform(-150, 150), rng.uniform(-40, 60),
                                                                   -rng.uniform(450, 650)))
        images.append(render_body_image(view, body, seed=k))
    outcomes: dict[str, Counter] = {"right clicks": Counter(), "one id wrong": Counter()}
    found, seconds, n = [], [], 0
    while n < sets:
        image = images[n % len(images)]
        pick = rng.choice(ids, 4, replace=False)
        if click_spread(xyz[np.searchsorted(ids, pick)], xyz) < 0.5:
            continue
        clicks = {int(i): tuple(image.pixels[ids == i][0] + rng.uniform(-3, 3, 2)) for i in pick}
        kind = "one id wrong" if n % 2 else "right clicks"
        if n % 2:
            j = int(rng.choice(pick))
            d = np.linalg.norm(xyz - xyz[ids == j], axis=1)
            d[ids == j] = np.inf
            neighbour = int(ids[np.argmin(d)])
            if neighbour in clicks:
                continue
            clicks[neighbour] = clicks.pop(j)
        n += 1
        t0 = time.perf_counter()
        try:
            match = find_body(image.image, body, clicks)
        except ClickError:
            outcomes[kind]["refused"] += 1
            seconds.append(time.perf_counter() - t0)
            continue
        seconds.append(time.perf_counter() - t0)
        nearest = ids[np.argmin(np.linalg.norm(image.pixels[None] - match.pixels[:, None], axis=2), axis=1)]
        wrong = int(np.sum(nearest != match.ids))
        outcomes[kind]["some id wrong" if wrong else "every id right"] += 1
        if not wrong and kind == "right clicks":
            found.append(len(match.ids) / image.visible.sum())
    print(f"{sets} click sets over {len(images)} rendered views (seed {seed}); {np.median(seconds):.2f} s per image "
          f"(median)")
    for kind, counts in outcomes.items():
        print(f"  {kind:13}: every id right {counts['every id right']:3d}, some id wrong {counts['some id wrong']:3d}, "
              f"refused {counts['refused']:3d}")
    print(f"  right clicks identified: {np.mean(found):.1%} of the visible points on average "
          f"(lowest {np.min(found):.1%})")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sets", type=int, default=80)
    parser.add_argument("--seed", type=int, default=11)
    args = parser.parse_args()
    main(args.sets, args.seed)
