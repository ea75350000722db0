"""The start of a long chain for refine-colmap: blocks slid outward from the middle.

A long chain (mount camera, more than CHAIN_MIN_FRAMES frames, short tracks: a strip survey) starts
otherwise: COLMAP's pinhole model of it is bent (measured on the simulated 100-image strip: it turns
~120 deg end to end, its local scale 44 % off the end-to-end bar's), and LM from it crawls along the
chain's soft bending mode (1.45 px, points 1.3 m after 100 iterations); so did LM on blocks grown to
the whole chain. The start slides instead (:func:`slid_start`): the FIRST_BLOCK_FRAMES frames
nearest the middle are refined (the distance held at the middle start distance, the normal and
intrinsics free), then SLIDE_NEW_FRAMES frames at a time, those that see the most refined points,
each placed by the similarity that carries the refined points it sees from COLMAP's model onto their
refined places (:func:`aligned`), are refined with their points, the refined frames that see them
held (the window and intrinsics too): every solve is small, starts near its optimum and converges in
a few iterations. Then the chain is rescaled to the bar (with the port distance: the images fix
distance / scale, not each) and refined with everything free, from within the noise of the optimum.
No distance search on that path; the other candidates remain the restarts.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np

from ari_sfm.colmap import adapter
from ari_sfm.geometry import Pose

from .problem import State
from .steps import BlockStep

log = logging.getLogger(__name__)

CHAIN_MIN_FRAMES = 41  # a model with more frames than this is a long chain: its start slides from a middle block
CHAIN_MAX_TRACK_FRACTION = 0.15  # ... when a point is seen, on average, in less than this fraction of the images
#   (simulated strips: 100 images 0.045, 200 images 0.03; the 100-image grid 0.30: it converges from
#   COLMAP's start with the distance search, 2x faster than through blocks, to the same 0.83 mm)
FIRST_BLOCK_FRAMES = 30  # the first block: the frames nearest the middle (a block this size converges from COLMAP's)
SLIDE_NEW_FRAMES = 10  # each later block refines this many new frames (with the refined ones they see held;
#   200-image strip: 20 converged too; 30 took in so much of the input's bend that blocks stopped bent or failed)
SLIDE_RETRY_COST = 4.0  # a block ending above this times the first block's cost per observation is taken again
BLOCK_ITERATIONS = 100  # LM iterations per block at most (a converged block stops earlier)
BLOCK_TOLERANCE = 1e-7  # a block's LM stops when a step lowers its cost by less than this fraction
ALIGN_MIN_POINTS = 10  # a frame is aligned by the refined points it sees when it sees at least this many
ALIGN_MIN_SPREAD = 0.2  # ... and their second principal spread is at least this fraction of the first
BLOCK_MIN_VIEWS = 2  # a point is in a block when block images see it this many times


@dataclass(frozen=True)
class Block:
    """A part of the model: its sub-model and the indices of its frames, images and points in the whole."""

    model: adapter.ColmapModel
    frames: np.ndarray
    images: np.ndarray
    points: np.ndarray


def make_block(model: adapter.ColmapModel, frames: np.ndarray, points: np.ndarray | None = None) -> Block:
    """The sub-model of ``frames``: their images, the points they see BLOCK_MIN_VIEWS times or more, those observations.

    Frames left with no observation are dropped.

    Args:
        model: the whole model.
        frames: the frames' indices.
        points: a mask of the points that may be in it (None: any).

    Returns:
        The block.
    """
    F, P = len(model.frame_ids), len(model.point3D_ids)
    fkeep = np.zeros(F, bool)
    fkeep[frames] = True
    for _ in range(3):  # dropping a frame can drop points seen by the others: until stable
        ikeep = fkeep[model.image_frame]
        obs = ikeep[model.obs_image]
        pkeep = np.bincount(model.obs_point[obs], minlength=P) >= BLOCK_MIN_VIEWS
        if points is not None:
            pkeep &= points
        obs &= pkeep[model.obs_point]
        seen = np.bincount(model.image_frame[model.obs_image[obs]], minlength=F) > 0
        if np.all(seen[fkeep]):
            break
        fkeep &= seen
    images, points = np.flatnonzero(ikeep), np.flatnonzero(pkeep)
    new_frame, new_image, new_point = np.cumsum(fkeep) - 1, np.cumsum(ikeep) - 1, np.cumsum(pkeep) - 1
    sub = replace(model, frame_ids=model.frame_ids[fkeep],
                  rig_from_world=tuple(model.rig_from_world[f] for f in np.flatnonzero(fkeep)),
                  image_ids=model.image_ids[images], image_names=tuple(model.image_names[i] for i in images),
                  image_camera=model.image_camera[images], image_frame=new_frame[model.image_frame[images]],
                  sensor_from_rig=tuple(model.sensor_from_rig[i] for i in images),
                  point3D_ids=model.point3D_ids[points], xyz=model.xyz[points],
                  obs_image=new_image[model.obs_image[obs]], obs_point=new_point[model.obs_point[obs]],
                  obs_uv=model.obs_uv[obs],
                  image_is_ref=None if model.image_is_ref is None else model.image_is_ref[images])
    return Block(sub, np.flatnonzero(fkeep), images, points)


def block_state(state: State, block: Block) -> State:
    """The state's values of a block's variables.

    Args:
        state: the whole state.
        block: the block.

    Returns:
        The block's state.
    """
    return replace(state, rig_from_world=tuple(state.rig_from_world[f] for f in block.frames),
                   sensor_from_rig=tuple(state.sensor_from_rig[i] for i in block.images), xyz=state.xyz[block.points])


def frame_centres(state: State) -> np.ndarray:
    return np.array([-p.R.T @ p.t for p in state.rig_from_world])


def with_block(state: State, block: Block, refined: State) -> State:
    """The whole state with a block's refined values written in.

    Args:
        state: the whole state.
        block: the block.
        refined: the block's refined state (its intrinsics and window are taken too).

    Returns:
        The whole state with the block's frames, images' sensors and points.
    """
    frames, sensors, xyz = list(state.rig_from_world), list(state.sensor_from_rig), state.xyz.copy()
    for k, f in enumerate(block.frames):
        frames[f] = refined.rig_from_world[k]
    for k, i in enumerate(block.images):
        sensors[i] = refined.sensor_from_rig[k]
    xyz[block.points] = refined.xyz
    return replace(refined, rig_from_world=tuple(frames), sensor_from_rig=tuple(sensors), xyz=xyz)


def aligned(model: adapter.ColmapModel, ref: State, state: State, refined: np.ndarray, frames: np.ndarray,
             points: np.ndarray | None = None) -> State:
    """``state`` with ``frames`` and the points not yet refined placed from ``ref`` by similarities.

    Each frame's similarity carries the refined points it sees from their place in ``ref`` to their place in
    ``state`` (a frame that sees fewer than ALIGN_MIN_POINTS of them, or nearly collinear ones: its nearest such
    frame's); a point takes the mean of its frames' images. The start is built frame by frame from the input's
    local shape, so that a bend the input accumulated along a long chain is not carried beyond the refined part.

    Args:
        model: the whole model.
        ref: the input's start.
        state: the state with the refined part.
        refined: a mask of the refined points.
        frames: the indices of the frames to place.
        points: a mask of the points that may be placed (None: any).

    Returns:
        The state with those frames and points placed.
    """
    from .truth import similarity

    F = len(model.frame_ids)
    frame_of_obs = model.image_frame[model.obs_image]
    placed = ~refined if points is None else ~refined & points
    needed = np.zeros(F, bool)  # the frames placed and those that see a point placed
    needed[frames] = True
    needed[frame_of_obs[placed[model.obs_point]]] = True
    by_frame = np.argsort(frame_of_obs, kind="stable")
    starts = np.searchsorted(frame_of_obs[by_frame], np.arange(F + 1))
    points_of = {int(f): model.obs_point[by_frame[starts[f]:starts[f + 1]]] for f in np.flatnonzero(needed)}
    sims: dict[int, tuple[float, np.ndarray, np.ndarray]] = {}
    for f, seen in points_of.items():
        pts = np.unique(seen[refined[seen]])
        if len(pts) >= ALIGN_MIN_POINTS:
            spread = np.sqrt(np.maximum(np.linalg.eigvalsh(np.cov(ref.xyz[pts].T)), 0.0))
            if spread[1] >= ALIGN_MIN_SPREAD * spread[2]:
                sims[f] = similarity(ref.xyz[pts], state.xyz[pts])
    if not sims:
        return state
    centres = frame_centres(ref)
    have = np.array(sorted(sims))
    nearest = {f: int(have[np.argmin(np.linalg.norm(centres[have] - centres[f], axis=1))]) for f in points_of}
    sim_of = {f: sims[f if f in sims else nearest[f]] for f in points_of}
    poses = list(state.rig_from_world)
    for f in frames:
        s, R, t = sim_of[int(f)]
        pose = ref.rig_from_world[f]  # X_rig = R_f X + t_f with X = R^T (X' - t) / s; the rig frame scaled by s
        poses[f] = Pose(pose.R @ R.T, s * pose.t - pose.R @ R.T @ t)
    moved = np.zeros((len(ref.xyz), 3))  # a placed point: the mean of its frames' similarities
    for f, (s, R, t) in sim_of.items():
        p = points_of[f][placed[points_of[f]]]
        np.add.at(moved, p, s * ref.xyz[p] @ R.T + t)
    count = np.bincount(model.obs_point[placed[model.obs_point]], minlength=len(ref.xyz))
    xyz = state.xyz.copy()
    rest = count > 0
    xyz[rest] = moved[rest] / count[rest, None]
    return replace(state, rig_from_world=tuple(poses), xyz=xyz)


def first_block(model: adapter.ColmapModel, state: State, mount: str) -> Block | None:
    """The first block of a long chain: the FIRST_BLOCK_FRAMES frames nearest the middle of the frame centres.

    A long chain: mount camera, more than CHAIN_MIN_FRAMES frames, a point seen in less than
    CHAIN_MAX_TRACK_FRACTION of the images on average.

    Args:
        model: the whole model.
        state: the start state (its frame centres).
        mount: ``camera`` or ``world``.

    Returns:
        The block; None for a shorter model, mount world (a window fixed in the world does not move with the
        aligned frames) or when the block lacks a camera.
    """
    if len(model.frame_ids) <= CHAIN_MIN_FRAMES or mount != "camera":
        return None
    if len(model.obs_image) / max(len(model.point3D_ids), 1) >= CHAIN_MAX_TRACK_FRACTION * len(model.image_ids):
        return None  # long tracks tie the model together: not a chain
    centres = frame_centres(state)
    block = make_block(model, np.argsort(np.linalg.norm(centres - np.median(centres, axis=0), axis=1),
                                     kind="stable")[:FIRST_BLOCK_FRAMES])
    return block if len(np.unique(block.model.image_camera)) == len(model.camera_ids) else None


def slid_start(model: adapter.ColmapModel, state: State, first: Block, make_solver,
               new_frames: int | None = None) -> tuple[State, list[BlockStep]]:
    """A long chain's start by sliding blocks.

    ``first`` is refined from ``state``, then again and again the ``new_frames`` frames that see the most
    refined points, aligned to them (:func:`aligned`), with their points and the refined frames that see
    ALIGN_MIN_POINTS of those, held, until every frame is refined. Every solve is small and starts near its
    optimum; a block that ends above SLIDE_RETRY_COST times the first block's cost per observation is dropped
    and taken again with half as many new frames.

    Args:
        model: the whole model.
        state: the input's start.
        first: the first block (:func:`first_block`).
        make_solver: ``make_solver(block_model, held)`` -> a Solver; ``held`` None for the first block, else the
            indices in the block of its held frames.
        new_frames: frames new to each later block (None: SLIDE_NEW_FRAMES).

    Returns:
        The start and the blocks' records.
    """
    F, P = len(model.frame_ids), len(model.point3D_ids)
    step = new_frames or SLIDE_NEW_FRAMES
    seen = np.zeros((F, P), bool)
    seen[model.image_frame[model.obs_image], model.obs_point] = True
    done, refined = np.zeros(F, bool), np.zeros(P, bool)
    ref, block, held, floor = state, first, None, None
    blocks: list[BlockStep] = []
    while True:
        res = make_solver(block.model, held).run(block_state(state, block), BLOCK_ITERATIONS,
                                                 relative_tolerance=BLOCK_TOLERANCE)
        per_observation = res.cost / len(block.model.obs_point)
        blocks.append(BlockStep(len(block.frames), 0 if held is None else len(held), len(block.points), res.cost,
                                res.iterations, res.linearizations))
        log.info("refine-colmap: block of %d frames (%d held), %d points3D: cost %.6g after %d iterations",
                 len(block.frames), blocks[-1].held, len(block.points), res.cost, res.iterations)
        if floor is not None and per_observation > SLIDE_RETRY_COST * floor and step > 1:
            step = max(1, step // 2)  # too far a step along the chain for the aligned start: a shorter one
            blocks[-1] = replace(blocks[-1], dropped=True)
            log.info("refine-colmap: that block did not converge to the noise: again with %d new frames", step)
        else:
            floor = per_observation if floor is None else floor
            state = with_block(state, block, res.state)
            done[block.frames], refined[block.points] = True, True
        if done.all():
            return aligned(model, ref, state, refined, np.zeros(0, int)), blocks  # points no block held
        sees = np.where(done, -1, seen[:, refined].sum(axis=1))
        new = np.argsort(-sees, kind="stable")[:min(step, int((~done).sum()))]
        theirs = np.asarray(seen[new].any(axis=0))  # the new frames' points, with every refined frame's view of them
        state = aligned(model, ref, state, refined, new, theirs)
        anchors = np.flatnonzero(done & (seen[:, theirs].sum(axis=1) >= ALIGN_MIN_POINTS))
        block = make_block(model, np.union1d(new, anchors), theirs)
        held = np.flatnonzero(np.isin(block.frames, anchors))
        if len(held) == 0:  # nothing refined sees them (a model in pieces): the block's own gauge
            held = None
