"""Drive the car yourself, with the arrow keys, in a window:

    python drive.py [--track 2067791 | --track racing/tracks/oval.csv] [--ghost AGENT] [--seed 0]
                    [--max-steps 200] [--fps 30] [--no-oracle] [--track-scale S] [--track-closed | --track-open]

Up accelerates (full throttle), down brakes (throttle -1), neither holds the throttle at 0 (a
target of half speed); left and right steer. AGENT (``score.py``'s kinds: a train.py run folder,
a Stable-Baselines3 ``model.zip``, ``module:function``, ``pure_pursuit``, ``ray_follower``)
drives the same episode beside you, drawn as a blue ghost car (it cannot touch you). At the end
the window shows your total reward beside the ghost's and the oracle's on the same track and
start state (the oracle takes about 10 ms a step, a notice says so while it drives;
``--no-oracle`` skips it), until you close the window or press Escape; the same lines are
printed. Escape or closing the window during the episode ends it early. Needs the ``render``
extra (``pip install -c constraints/cpu.txt -e '.[render]'``).
"""

from __future__ import annotations

import argparse
import os
import sys

from engine.budget import SEED, count
from racing.track_file import add_track_options

KEYS = ("up", "down", "left", "right")


def action_of(pressed: set[str]) -> list[float]:
    """[throttle, steering] of the arrow keys held."""
    throttle = (1.0 if "up" in pressed else 0.0) - (1.0 if "down" in pressed else 0.0)
    steer = (1.0 if "left" in pressed else 0.0) - (1.0 if "right" in pressed else 0.0)
    return [throttle, steer]


def play(track, seed: int = 0, ghost=None, max_steps: int = 200, fps: int = 30, oracle: bool = True,
         script: dict[int, list[tuple[str, bool]]] | None = None, hold: bool | None = None) -> dict:
    """One episode driven from the keyboard; returns the totals {"you", "ghost", "oracle"}.

    ``script`` ({step: [(key, down), ...]}) posts those key events before each step (how the tests
    drive it under SDL's dummy video driver). ``hold``: keep the end screen until the window is
    closed (or Escape, Enter or Q is pressed); default: unless scripted or without a display to
    close (SDL's dummy video driver)."""
    from racing.gym_env import RacingEnv
    from racing.render import Renderer, import_pygame

    pg = import_pygame()
    names = {pg.K_UP: "up", pg.K_DOWN: "down", pg.K_LEFT: "left", pg.K_RIGHT: "right"}
    keys_of = {v: k for k, v in names.items()}
    from racing.track_file import env_keywords

    where = env_keywords(track)
    env = RacingEnv(max_steps=max_steps, **where)
    shadow = RacingEnv(max_steps=max_steps, **where) if ghost is not None else None
    renderer = Renderer(env.config, human=True, fps=fps)
    pg.display.init()  # the event queue needs it before the first frame
    obs, _ = env.reset(seed=seed)
    if shadow is not None:
        ghost_obs, _ = shadow.reset(seed=seed)
        ghost.reset()
    pressed: set[str] = set()
    totals = {"you": 0.0, "ghost": 0.0 if ghost is not None else None}
    ghost_done, quit_early = False, False
    for step in range(max_steps):
        for key, down in (script or {}).get(step, []):
            pg.event.post(pg.event.Event(pg.KEYDOWN if down else pg.KEYUP, key=keys_of[key]))
        ghosts = [] if shadow is None else [(float(shadow.unwrapped.sim.x[0]), float(shadow.unwrapped.sim.y[0]),
                                             float(shadow.unwrapped.sim.theta[0]))]
        renderer.draw(env.unwrapped.sim, ghosts=ghosts,
                      extra=[f"you {totals['you']:.1f}" + ("" if ghost is None else f"   ghost {totals['ghost']:.1f}")])
        for event in pg.event.get():
            if event.type == pg.QUIT or (event.type == pg.KEYDOWN and event.key == pg.K_ESCAPE):
                quit_early = True
            elif event.type in (pg.KEYDOWN, pg.KEYUP) and event.key in names:
                (pressed.add if event.type == pg.KEYDOWN else pressed.discard)(names[event.key])
        if quit_early:
            break
        obs, reward, terminated, truncated, _ = env.step(action_of(pressed))
        totals["you"] += reward
        if shadow is not None and not ghost_done:
            ghost_obs, g_reward, g_term, g_trunc, _ = shadow.step(ghost.act(shadow, ghost_obs))
            totals["ghost"] += g_reward
            ghost_done = g_term or g_trunc
        if terminated or truncated:
            break
    if oracle and not quit_early:
        from racing.oracle import Oracle, drive

        renderer.draw(env.unwrapped.sim, extra=["", "The oracle is driving the same episode to compare;",
                                                f"about {max_steps / 100:.0f} s ({max_steps} steps at ~10 ms)..."])
        totals["oracle"] = drive(RacingEnv(max_steps=max_steps, **where), Oracle(), seed)
    lines = [f"you: {totals['you']:.1f}"]
    if totals["ghost"] is not None:
        lines.append(f"ghost ({ghost.name}): {totals['ghost']:.1f}")
    if "oracle" in totals:
        lines.append(f"oracle: {totals['oracle']:.1f}")
    renderer.draw(env.unwrapped.sim, extra=["", *lines, "", "(close the window, or press Escape)"])
    print("; ".join(lines), flush=True)  # the result now, not when the window closes
    if hold if hold is not None else (script is None and pg.display.get_driver() not in ("dummy", "offscreen")):
        _wait_for_close(pg)  # a window someone can close (no display: SDL's dummy or offscreen driver, no wait)
    renderer.close()
    return totals


def display_problem(environ=None, platform: str | None = None) -> str | None:
    """Why no window can open here, in one line (None: one can, or the user chose SDL's video driver)."""
    environ = os.environ if environ is None else environ
    platform = sys.platform if platform is None else platform
    if environ.get("SDL_VIDEODRIVER"):
        return None
    if platform.startswith(("linux", "freebsd", "openbsd")) and not (environ.get("DISPLAY") or
                                                                       environ.get("WAYLAND_DISPLAY")):
        return ("no display to open a window on (DISPLAY and WAYLAND_DISPLAY are unset): driving needs one; "
                "to watch an agent without a display, film it: python score.py AGENT --video agent.gif")
    return None


def _wait_for_close(pg) -> None:
    """Until the window is closed or Escape, Enter or Q is pressed."""
    done = {pg.K_ESCAPE, pg.K_RETURN, pg.K_q}
    while True:
        event = pg.event.wait(200)  # NOEVENT after 200 ms: the loop stays responsive to signals
        if event.type == pg.QUIT or (event.type == pg.KEYDOWN and event.key in done):
            return


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--track", default="2067791", help="a track seed or a track file (default: 2067791)")
    add_track_options(parser)
    parser.add_argument("--ghost", default=None, help="an agent to race against, drawn as a ghost")
    parser.add_argument("--seed", type=SEED, default=0, help="the start state's seed")
    parser.add_argument("--max-steps", type=count(1, 100_000), default=200)
    parser.add_argument("--fps", type=count(1, 100_000), default=30)
    parser.add_argument("--no-oracle", action="store_true", help="do not run the oracle at the end")
    args = parser.parse_args(argv)
    from racing.track_file import TrackFileError, parse_track

    try:
        track = parse_track("--track", args.track, args.track_scale, args.track_closed)
    except TrackFileError as err:
        parser.error(str(err))
    if not 0 <= args.seed < 2**32 or args.max_steps < 1 or args.fps < 1:
        parser.error("--seed must be in [0, 2**32), --max-steps and --fps at least 1")
    ghost = None
    if args.ghost is not None:
        from engine import numerics

        numerics.apply(numerics.DEFAULT)
        from benchmark.protocol import AgentError, load_agent

        try:
            ghost = load_agent(args.ghost)
        except AgentError as err:
            print(f"drive: {err}", file=sys.stderr)
            return 2
    problem = display_problem()
    if problem:
        print(f"drive: {problem}", file=sys.stderr)
        return 2
    try:
        play(track, args.seed, ghost, args.max_steps, args.fps, oracle=not args.no_oracle)
    except ImportError as err:
        print(f"drive: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("drive", main))
