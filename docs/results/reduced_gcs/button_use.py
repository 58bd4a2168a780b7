"""What each pair does on Grounded Coord. Simple: button presses, deliveries and return, per starting recipe.

    python docs/results/reduced_gcs/button_use.py STUDY_DIR/runs/sp STUDY_DIR/runs/fcp [--episodes 50] [--seeds 4]

Every ordered pair of final checkpoints (seat 0 from any run, seat 1 from any run) plays N fresh episodes with
sampled actions and a fixed key. On this layout seat 0 starts in the left room with the recipe indicator, the
recipe button and only the unused ingredient 2; seat 1 starts in the right room with the pot, the plates,
ingredients 0 and 1 and the delivery window. So only seat 0 can press the button (it shows the recipe at the
button for BUTTON_ACTIVE_TIME steps, for BUTTON_COST) and only seat 1 can cook. That splits a team's return
into its parts: 20 per correct delivery, -20 per wrong one, -BUTTON_COST per press.

A press is counted when the button's timer rises above where the previous step's countdown would have left it:
a press leaves the timer at BUTTON_ACTIVE_TIME - 1 after the step's tick, one above a countdown from there, so
a press on the step right after another one counts too. The wrong deliveries are derived from the return with
these counts; a return that does not split into whole deliveries stops the script.
"""

import argparse
import functools
from pathlib import Path

import jax
import numpy as np

from ocv2 import items
from ocv2.items import Static
from population.evaluation import play_seats
from population.policy import load, policy_env
from population.xp import recipe_names


@functools.lru_cache
def compiled_play(env, episodes: int):
    return jax.jit(
        lambda seats_params, applies, hiddens, key: play_seats(
            tuple(zip(applies, seats_params, hiddens)), env, key, episodes, keep_every=1
        ),
        static_argnums=(1, 2),
    )


def signal_counters(env) -> np.ndarray:
    """bool[H, W]: counters that seat 0 can reach and seat 1 can see from somewhere in its room. Items
    placed there are the one thing besides the button that seat 0 can show seat 1 (agents in the two
    rooms are never within each other's view window)."""
    rooms = np.asarray(env.layout.room_labels)
    state = env.reset(jax.random.PRNGKey(0))[1]
    static = np.asarray(state.grid[..., 0])
    height, width = rooms.shape
    room0 = rooms == rooms[int(state.agents.y[0]), int(state.agents.x[0])]
    room1 = rooms == rooms[int(state.agents.y[1]), int(state.agents.x[1])]
    radius = env.config.view_radius
    out = np.zeros_like(room0)
    y1, x1 = np.nonzero(room1)
    for y, x in zip(*np.nonzero(static == Static.WALL)):
        near0 = any(
            room0[y + dy, x + dx]
            for dy, dx in ((0, 1), (1, 0), (0, -1), (-1, 0))
            if 0 <= y + dy < height and 0 <= x + dx < width
        )
        seen1 = np.any((np.abs(y1 - y) <= radius) & (np.abs(x1 - x) <= radius))
        out[y, x] = near0 and seen1
    return out


def pair_record(seat0, seat1, env, counters: np.ndarray, episodes: int, key) -> dict:
    """``counters``: ``signal_counters(env)``, computed once by the caller."""
    play = compiled_play(env, episodes)
    played = play((seat0.params, seat1.params), (seat0.apply, seat1.apply), (seat0.hidden_size, seat1.hidden_size), key)
    grid = np.asarray(played.states.grid)  # [R, T, H, W, 3]
    ys, xs = np.nonzero(counters)
    shown = (grid[:, :, ys, xs, 1] != 0).mean(axis=1)  # [R, counters]: share of steps with an item there
    button = grid[..., 0] == Static.BUTTON
    timer = np.where(button, grid[..., 2], 0).max(axis=(-1, -2))  # [R, T]
    presses = (timer[:, 1:] > np.maximum(timer[:, :-1] - 1, 0)).sum(axis=1)
    correct = np.asarray(played.states.new_correct_delivery).sum(axis=1)
    returns = np.asarray(played.returns).reshape(-1)
    delivery = items.DELIVERY_REWARD
    wrong = (delivery * correct - items.BUTTON_COST * presses - returns) / delivery
    if not np.allclose(wrong, np.round(wrong)):  # a reward this split does not know of, or a missed press
        raise SystemExit(f"returns {returns[wrong != np.round(wrong)][:5]} do not split into deliveries and presses")
    recipe = np.asarray(played.start_recipe).reshape(-1)
    return {
        "presses": presses,
        "shown": shown,
        "correct": correct,
        "wrong": wrong,
        "returns": returns,
        "recipe": recipe,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", help="run directories (their final checkpoints play every pairing)")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seeds", type=int, default=4)
    args = parser.parse_args()
    policies = [(f"{Path(run).name}/{seed}", load(run, seed=seed)) for run in args.runs for seed in range(args.seeds)]
    env = policy_env(policies[0][1].env)
    names = recipe_names(env)
    counters = signal_counters(env)
    labels = [f"item on ({x}, {y})" for y, x in zip(*np.nonzero(counters))]
    print(
        "| seat 0 | seat 1 | recipe | episodes | button presses | "
        + " | ".join(labels)
        + " | correct deliveries | wrong deliveries | return |"
    )
    print("|---|---|---|---:|---:|" + "---:|" * len(labels) + "---:|---:|---:|")
    key = jax.random.PRNGKey(11)
    for name0, seat0 in policies:
        for name1, seat1 in policies:
            rec = pair_record(seat0, seat1, env, counters, args.episodes, key)
            for code in sorted(set(rec["recipe"].tolist())):
                mask = rec["recipe"] == code
                cells = [rec["presses"][mask].mean(), *rec["shown"][mask].mean(axis=0)]
                cells += [rec[k][mask].mean() for k in ("correct", "wrong")]
                print(
                    f"| {name0} | {name1} | {names[code]} | {mask.sum()} | "
                    + " | ".join(f"{c:.2f}" for c in cells)
                    + f" | {rec['returns'][mask].mean():.1f} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()
