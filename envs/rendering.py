"""Rendering of task-allocation environments: ``rgb_array`` frames, ``ansi`` text and episode GIFs."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium as gym
import numpy as np
from PIL import Image, ImageDraw

if TYPE_CHECKING:
    from envs.core import TaskAllocEnv

SIZE = 400
MARGIN = 20
TASK_COLOR = (214, 39, 40)
ENTITY_FREE = (31, 119, 180)
ENTITY_BUSY = (255, 127, 14)
LINE_COLOR = (120, 120, 120)


def _layout(env: TaskAllocEnv) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates of entities (N, 2) and task slots (M, 2)."""
    N, M = env.max_entities, env.max_tasks
    if env.has_positions:
        extent = float(env.grid_size or max(env._pos.max(), env._tpos.max(), 1) + 1)
        scale = (SIZE - 2 * MARGIN) / max(extent - 1, 1)
        jitter = np.stack([np.cos(np.arange(N) * 2.4), np.sin(np.arange(N) * 2.4)], 1) * min(scale * 0.3, 6)
        ent = MARGIN + env._pos * scale + jitter
        task = MARGIN + env._tpos * scale
    else:  # bipartite layout: entities on the left, tasks on the right
        ent = np.stack([np.full(N, SIZE * 0.2), np.linspace(MARGIN, SIZE - MARGIN, N)], 1)
        task = np.stack([np.full(M, SIZE * 0.8), np.linspace(MARGIN * 2, SIZE - MARGIN * 2, M)], 1)
    return ent, task


def render_rgb(env: TaskAllocEnv) -> np.ndarray:
    """A (SIZE, SIZE, 3) uint8 frame: tasks as red squares (size ~ reward), entities as dots (orange when
    committed), a grey line from each committed entity to its task."""
    img = Image.new("RGB", (SIZE, SIZE), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    if env.has_positions and env.grid_size and env.grid_size <= 20:
        step = (SIZE - 2 * MARGIN) / max(env.grid_size - 1, 1)
        for k in range(env.grid_size):
            p = MARGIN + k * step
            draw.line([(p, MARGIN), (p, SIZE - MARGIN)], fill=(235, 235, 235))
            draw.line([(MARGIN, p), (SIZE - MARGIN, p)], fill=(235, 235, 235))
    ent, task = _layout(env)
    assigned = env._assigned if env.busy else env.applied_action()
    for i in np.flatnonzero(env._present0).tolist():
        slot = int(assigned[i])
        if 0 <= slot < env.max_tasks and env._occupied[slot]:
            draw.line([tuple(ent[i]), tuple(task[slot])], fill=LINE_COLOR)
    rmax = max(float(env._reward.max(initial=0.0)), 1e-6)
    for slot in np.flatnonzero(env._occupied).tolist():
        r = 4 + 8 * float(env._reward[slot]) / rmax
        x, y = task[slot]
        draw.rectangle([x - r, y - r, x + r, y + r], outline=TASK_COLOR, width=2)
    for k in np.flatnonzero(env._present0 & env._alive).tolist():
        x, y = ent[k]
        color = ENTITY_BUSY if env._assigned[k] >= 0 else ENTITY_FREE
        draw.ellipse([x - 2.5, y - 2.5, x + 2.5, y + 2.5], fill=color)
    draw.text((4, 2), f"t={env._t}", fill=(0, 0, 0))
    return np.asarray(img, dtype=np.uint8)


def render_ansi(env: TaskAllocEnv) -> str:
    """Text summary: one line per occupied task slot, then the entity counts."""
    rem = env._rem
    lines = [f"t={env._t}  tasks (slot: reward | remaining demand | team | position)"]
    for j in np.flatnonzero(env._occupied):
        team = np.flatnonzero(env._assigned == j).tolist()
        demand = " ".join(f"{v:.1f}" for v in rem[j])
        pos = f" @({env._tpos[j, 0]},{env._tpos[j, 1]})" if env.has_positions else ""
        lines.append(f"  [{j}] {env._reward[j]:.2f} | {demand} | {team}{pos}")
    free = int(env._free.sum())
    busy = int((env._assigned >= 0).sum())
    used = int((env._present0 & ~env._alive).sum())
    lines.append(f"entities: {free} free, {busy} committed, {used} used up, of {env.n_entities}")
    return "\n".join(lines) + "\n"


def save_gif(
    env: gym.Env,
    policy: Callable[[dict[str, np.ndarray]], Any] | None,
    path: str | Path,
    seed: int | None = 0,
    max_steps: int = 200,
    fps: int = 4,
) -> tuple[Path, float]:
    """Run one episode and write it as an animated GIF.

    :param env: an environment created with ``render_mode="rgb_array"``
    :param policy: maps an observation to an action (e.g. ``lambda obs: model.predict(obs, deterministic=True)[0]``);
        None samples random valid allocations
    :param path: output file
    :param seed: reset seed
    :param max_steps: stop after this many steps
    :param fps: frames per second
    :return: the path written and the episode return
    """
    if env.render_mode != "rgb_array":
        raise ValueError(f"save_gif needs render_mode='rgb_array', got {env.render_mode!r}")
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    frames = [Image.fromarray(env.render())]  # type: ignore[arg-type]
    total = 0.0
    for _ in range(max_steps):
        action = policy(obs) if policy is not None else random_valid_action(obs, rng)
        obs, reward, terminated, truncated, _ = env.step(action)
        total += float(reward)
        frames.append(Image.fromarray(env.render()))  # type: ignore[arg-type]
        if terminated or truncated:
            break
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0)
    return path, total


def random_valid_action(obs: dict[str, np.ndarray], rng: np.random.Generator) -> np.ndarray:
    """Uniformly random allocation that respects ``obs["action_mask"]`` (each entity: a valid task or unassigned)."""
    mask = np.asarray(obs["action_mask"]).reshape(len(obs["entity_mask"]), -1).astype(bool)
    scores = rng.random(mask.shape) + mask  # valid choices score in [1, 2), invalid in [0, 1)
    return np.argmax(scores, axis=1)
