"""Rendering of task-allocation environments: ``rgb_array`` frames, ``ansi`` text and episode GIFs.

The renderers draw a :class:`RenderSnapshot` (``env.unwrapped.render_snapshot()``), never the env itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from PIL import Image, ImageDraw

SIZE = 400
MARGIN = 20
TASK_COLOR = (214, 39, 40)
ENTITY_FREE = (31, 119, 180)
ENTITY_BUSY = (255, 127, 14)
LINE_COLOR = (120, 120, 120)


@dataclass(frozen=True)
class RenderSnapshot:
    """What a picture of one state needs (N padded entities, M task slots)."""

    t: int  # step
    has_positions: bool  # entities and tasks have cells (else a bipartite layout)
    grid_size: int | None  # side of the grid (None: the extent of the cells)
    n_entities: int  # real (unpadded) entities
    entity_pos: np.ndarray  # (N, 2) cells
    task_pos: np.ndarray  # (M, 2) cells
    present: np.ndarray  # (N,) bool: real entity
    alive: np.ndarray  # (N,) bool: not used up
    free: np.ndarray  # (N,) bool: free to be assigned
    assigned: np.ndarray  # (N,) task slot the entity is committed to, −1 if none
    shown: np.ndarray  # (N,) task slot to draw a line to (the commitment, or the last step's choice), −1 if none
    occupied: np.ndarray  # (M,) bool: slot holds a task
    reward: np.ndarray  # (M,) current rewards
    remaining: np.ndarray  # (M, K) remaining demand


def _layout(snap: RenderSnapshot) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates of entities (N, 2) and task slots (M, 2)."""
    N, M = len(snap.present), len(snap.occupied)
    if snap.has_positions:
        extent = float(snap.grid_size or max(snap.entity_pos.max(), snap.task_pos.max(), 1) + 1)
        scale = (SIZE - 2 * MARGIN) / max(extent - 1, 1)
        jitter = np.stack([np.cos(np.arange(N) * 2.4), np.sin(np.arange(N) * 2.4)], 1) * min(scale * 0.3, 6)
        return MARGIN + snap.entity_pos * scale + jitter, MARGIN + snap.task_pos * scale
    # bipartite layout: entities on the left, tasks on the right
    ent = np.stack([np.full(N, SIZE * 0.2), np.linspace(MARGIN, SIZE - MARGIN, N)], 1)
    task = np.stack([np.full(M, SIZE * 0.8), np.linspace(MARGIN * 2, SIZE - MARGIN * 2, M)], 1)
    return ent, task


def render_rgb(snap: RenderSnapshot) -> np.ndarray:
    """A (SIZE, SIZE, 3) uint8 frame: tasks as red squares (size ~ reward), entities as dots (orange when
    committed), a grey line from each committed entity to its task."""
    img = Image.new("RGB", (SIZE, SIZE), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    if snap.has_positions and snap.grid_size and snap.grid_size <= 20:
        step = (SIZE - 2 * MARGIN) / max(snap.grid_size - 1, 1)
        for k in range(snap.grid_size):
            p = MARGIN + k * step
            draw.line([(p, MARGIN), (p, SIZE - MARGIN)], fill=(235, 235, 235))
            draw.line([(MARGIN, p), (SIZE - MARGIN, p)], fill=(235, 235, 235))
    ent, task = _layout(snap)
    for i in np.flatnonzero(snap.present).tolist():
        slot = int(snap.shown[i])
        if slot >= 0 and snap.occupied[slot]:
            draw.line([tuple(ent[i]), tuple(task[slot])], fill=LINE_COLOR)
    rmax = max(float(snap.reward.max(initial=0.0)), 1e-6)
    for slot in np.flatnonzero(snap.occupied).tolist():
        r = 4 + 8 * float(snap.reward[slot]) / rmax
        x, y = task[slot]
        draw.rectangle([x - r, y - r, x + r, y + r], outline=TASK_COLOR, width=2)
    for k in np.flatnonzero(snap.present & snap.alive).tolist():
        x, y = ent[k]
        color = ENTITY_BUSY if snap.assigned[k] >= 0 else ENTITY_FREE
        draw.ellipse([x - 2.5, y - 2.5, x + 2.5, y + 2.5], fill=color)
    draw.text((4, 2), f"t={snap.t}", fill=(0, 0, 0))
    return np.asarray(img, dtype=np.uint8)


def render_ansi(snap: RenderSnapshot) -> str:
    """Text summary: one line per occupied task slot, then the entity counts."""
    lines = [f"t={snap.t}  tasks (slot: reward | remaining demand | team | position)"]
    for j in np.flatnonzero(snap.occupied):
        team = np.flatnonzero(snap.assigned == j).tolist()
        demand = " ".join(f"{v:.1f}" for v in snap.remaining[j])
        pos = f" @({snap.task_pos[j, 0]},{snap.task_pos[j, 1]})" if snap.has_positions else ""
        lines.append(f"  [{j}] {snap.reward[j]:.2f} | {demand} | {team}{pos}")
    free = int(snap.free.sum())
    busy = int((snap.assigned >= 0).sum())
    used = int((snap.present & ~snap.alive).sum())
    lines.append(f"entities: {free} free, {busy} committed, {used} used up, of {snap.n_entities}")
    return "\n".join(lines) + "\n"


def save_gif(
    env: gym.Env,
    policy: Any,
    path: str | Path,
    seed: int | None = 0,
    max_steps: int = 200,
    fps: int = 4,
) -> tuple[Path, float]:
    """Run one episode and write it as an animated GIF.

    :param env: an environment created with ``render_mode="rgb_array"``
    :param policy: anything with SB3's ``predict`` (a model or a baseline allocator, run deterministically), a function
        from an observation to an action, or None for random valid allocations
    :param path: output file
    :param seed: reset seed
    :param max_steps: stop after this many steps
    :param fps: frames per second
    :return: the path written and the episode return
    """
    if env.render_mode != "rgb_array":
        raise ValueError(f"save_gif needs render_mode='rgb_array', got {env.render_mode!r}")
    if policy is not None and hasattr(policy, "predict"):  # an SB3 model or a baseline allocator
        model = policy

        def policy(obs: dict[str, np.ndarray]) -> Any:
            return model.predict(obs, deterministic=True)[0]

    elif policy is not None and not callable(policy):
        raise TypeError(f"policy must map an observation to an action or have predict(), got {type(policy).__name__}")
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    frames = [captioned(env.render(), 0.0)]  # type: ignore[arg-type]
    total = 0.0
    for _ in range(max_steps):
        action = policy(obs) if policy is not None else random_valid_action(obs, rng)
        obs, reward, terminated, truncated, _ = env.step(action)
        total += float(reward)
        frames.append(captioned(env.render(), total))  # type: ignore[arg-type]
        if terminated or truncated:
            break
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0)
    return path, total


#: Height of the strip under each GIF frame that holds its legend and the return so far.
CAPTION = 34


def captioned(frame: np.ndarray, total: float) -> Image.Image:
    """``frame`` with a strip below it: the legend of :func:`render_rgb`'s marks and the episode's return so far."""
    height, width = frame.shape[:2]
    img = Image.new("RGB", (width, height + CAPTION), (255, 255, 255))
    img.paste(Image.fromarray(frame), (0, 0))
    draw = ImageDraw.Draw(img)
    y = height + 4
    draw.rectangle([6, y + 1, 14, y + 9], outline=TASK_COLOR, width=2)
    draw.text((18, y), "task (size: reward)", fill=(0, 0, 0))
    draw.ellipse([140, y + 2, 146, y + 8], fill=ENTITY_FREE)
    draw.text((150, y), "free", fill=(0, 0, 0))
    draw.ellipse([190, y + 2, 196, y + 8], fill=ENTITY_BUSY)
    draw.text((200, y), "committed", fill=(0, 0, 0))
    draw.line([(272, y + 5), (290, y + 5)], fill=LINE_COLOR, width=2)
    draw.text((294, y), "assignment", fill=(0, 0, 0))
    draw.text((6, y + 15), f"return so far: {total:.1f}", fill=(0, 0, 0))
    return img


def random_valid_action(obs: dict[str, np.ndarray], rng: np.random.Generator) -> np.ndarray:
    """Uniformly random allocation that respects ``obs["action_mask"]`` (each entity: a valid task or unassigned)."""
    mask = np.asarray(obs["action_mask"]).reshape(len(obs["entity_mask"]), -1).astype(bool)
    scores = rng.random(mask.shape) + mask  # valid choices score in [1, 2), invalid in [0, 1)
    return np.argmax(scores, axis=1)
