"""Pictures of the racing task with pygame: a camera that follows a car, and whole-track views.

pygame is imported only when a picture is drawn (the ``render`` extra: ``RENDER_EXTRA``).
Rendering needs no screen: ``rgb_array`` draws off-screen, and ``human`` works under
``SDL_VIDEODRIVER=dummy`` too.
"""

from __future__ import annotations

import numpy as np

from racing.config import RacingConfig
from racing.track import Track, deg_to_rad

GRASS = (46, 94, 52)
ASPHALT = (92, 92, 98)
WALL = (240, 240, 240)
CHECKPOINT_LINE = (120, 120, 128)
FINISH = (250, 210, 60)
CAR = (220, 30, 30)
GHOST = (150, 170, 255)  # another car on the same track (drive.py: a policy racing the player)
RAY = (255, 220, 70)
TRAIL = (80, 170, 255)
TEXT = (255, 255, 255)
CAR_LENGTH, CAR_WIDTH = 24.0, 12.0  # pixels of the world


RENDER_EXTRA = "pip install -c constraints/cpu.txt -e '.[render]' (in the project's folder, in its environment)"


def import_pygame():
    try:
        import pygame
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise ImportError(f"rendering needs pygame, in the render extra: {RENDER_EXTRA}") from exc
    return pygame


def _car_outline(x: float, y: float, theta: float) -> np.ndarray:
    forward = np.array([np.sin(theta), np.cos(theta)])
    side = np.array([forward[1], -forward[0]])
    corners = [(1, 1), (1, -1), (-1, -1), (-1, 1)]
    return np.array([[x, y] + a * CAR_LENGTH / 2 * forward + b * CAR_WIDTH / 2 * side
                     for a, b in corners])


def ray_endpoints(x: float, y: float, theta: float, readings: np.ndarray,
                  config: RacingConfig) -> np.ndarray:
    """World coordinates where each ray ends (at the wall, or at full length), shape (R, 2)."""
    phi = deg_to_rad(90.0 + np.array(config.ray_angles_deg) - theta / np.pi * 180.0)
    distance = np.asarray(readings)[: config.num_rays] * config.ray_length
    return np.stack([x + np.cos(phi) * distance, y + np.sin(phi) * distance], axis=1)


class Canvas:
    """A pygame surface showing the world through an affine camera (y up)."""

    def __init__(self, size: tuple[int, int], centre: np.ndarray, scale: float):
        self.pg = import_pygame()
        self.surface = self.pg.Surface(size)
        self.size = size
        self.centre = np.asarray(centre, dtype=float)
        self.scale = scale

    def to_screen(self, points: np.ndarray) -> list[tuple[float, float]]:
        p = (np.asarray(points, dtype=float) - self.centre) * self.scale
        return [(self.size[0] / 2 + px, self.size[1] / 2 - py) for px, py in np.atleast_2d(p)]

    def track(self, track: Track) -> None:
        pg, s = self.pg, self.surface
        s.fill(GRASS)
        for i in range(track.num_checkpoints):
            pg.draw.polygon(s, ASPHALT, self.to_screen(track.checkpoint(i)))
        for i in range(1, track.num_checkpoints):
            pg.draw.line(s, CHECKPOINT_LINE, *self.to_screen([track.left_wall[i], track.right_wall[i]]))
        width = max(1, round(2 * self.scale))
        pg.draw.lines(s, WALL, False, self.to_screen(track.left_wall), width)
        pg.draw.lines(s, WALL, False, self.to_screen(track.right_wall), width)
        pg.draw.line(s, FINISH, *self.to_screen([track.left_wall[-1], track.right_wall[-1]]), width + 1)

    def trail(self, points: np.ndarray) -> None:
        if len(points) > 1:
            self.pg.draw.lines(self.surface, TRAIL, False, self.to_screen(points), 2)

    def car(self, x: float, y: float, theta: float, readings: np.ndarray | None,
            config: RacingConfig, colour: tuple = None) -> None:
        if readings is not None:
            origin = self.to_screen([[x, y]])[0]
            for end in self.to_screen(ray_endpoints(x, y, theta, readings, config)):
                self.pg.draw.line(self.surface, RAY, origin, end, 1)
                self.pg.draw.circle(self.surface, RAY, end, 3)
        outline = _car_outline(x, y, theta)
        colour = CAR if colour is None else colour
        if self.scale * CAR_LENGTH < 6:  # too small to see: draw a dot
            self.pg.draw.circle(self.surface, colour, self.to_screen([[x, y]])[0], 4)
        else:
            self.pg.draw.polygon(self.surface, colour, self.to_screen(outline))

    def text(self, lines: list[str]) -> None:
        pg = self.pg
        if not pg.font.get_init():
            pg.font.init()
        font = pg.font.Font(None, 20)
        for k, line in enumerate(lines):
            self.surface.blit(font.render(line, True, TEXT), (8, 8 + 18 * k))

    def rgb(self) -> np.ndarray:
        return np.ascontiguousarray(self.pg.surfarray.array3d(self.surface).transpose(1, 0, 2))


def track_view(track: Track, size: tuple[int, int] = (800, 600), margin: float = 0.05) -> Canvas:
    """A canvas framing a whole track, with the track drawn on it."""
    low, high = track.bounds()
    span = np.maximum(high - low, 1.0)
    scale = (1 - 2 * margin) * min(size[0] / span[0], size[1] / span[1])
    canvas = Canvas(size, (low + high) / 2, scale)
    canvas.track(track)
    return canvas


MAP_SIZE = 150  # pixels: the whole track in a frame's lower right corner, the car a dot on it


class Renderer:
    """Draws one car of a ``RacingSim`` with a camera that follows it (the paper's screenshot view),
    a map of the whole track in a corner (``MAP_SIZE``) and the car's figures as text."""

    def __init__(self, config: RacingConfig, human: bool = False, size: tuple[int, int] = (600, 600),
                 view: float = 1200.0, fps: int = 30):
        self.pg = import_pygame()
        self.config = config
        self.size = size
        self.scale = min(size) / view  # ``view`` world pixels across the shorter side
        self.human = human
        self.fps = fps
        self.window = None
        self.clock = None
        self._map: tuple[Track, Canvas] | None = None  # the last track's map, drawn once per track

    def draw(self, sim, car: int = 0, ghosts: list = (), extra: list[str] = ()) -> np.ndarray | None:
        """The frame of ``sim``'s car ``car``; ``ghosts``: (x, y, theta) of other cars to draw faintly
        (e.g. a policy's car on the same track); ``extra``: more lines of text."""
        x, y, theta = float(sim.x[car]), float(sim.y[car]), float(sim.theta[car])
        canvas = Canvas(self.size, (x, y), self.scale)
        canvas.track(sim.tracks[car])
        for gx, gy, gtheta in ghosts:
            canvas.car(gx, gy, gtheta, None, self.config, colour=GHOST)
        readings = sim.observe()[car]
        canvas.car(x, y, theta, readings, self.config)
        self._draw_map(canvas, sim.tracks[car], [(x, y, CAR), *[(gx, gy, GHOST) for gx, gy, _ in ghosts]])
        n = self.config.num_segments
        progress = sim.car_state(car)["progress"]
        lines = [f"speed {sim.speed[car]:5.1f}   checkpoint {sim.checkpoint[car]}/{n}   progress {progress:.0%}",
                 f"step {sim.t[car]}   crashes {sim.crashes[car]}"]
        if sim.tracks[car].closed:
            times = sim.lap_times[car]
            lines.append(f"lap {sim.laps[car] + 1}" + (f"   last {times[-1] * sim.STEP_SECONDS:.2f} s   best "
                                                       f"{min(times) * sim.STEP_SECONDS:.2f} s" if times else ""))
        canvas.text(lines + list(extra))
        if not self.human:
            return canvas.rgb()
        pg = self.pg
        if self.window is None:
            pg.display.init()
            self.window = pg.display.set_mode(self.size)
            pg.display.set_caption("racing")
            self.clock = pg.time.Clock()
        self.window.blit(canvas.surface, (0, 0))
        pg.event.pump()
        pg.display.flip()
        self.clock.tick(self.fps)
        return None

    def _draw_map(self, canvas: Canvas, track: Track, cars: list[tuple[float, float, tuple]]) -> None:
        """The whole track in the lower right corner of ``canvas``, each of ``cars`` (x, y, colour) a dot."""
        if self._map is None or self._map[0] is not track:
            self._map = (track, track_view(track, (MAP_SIZE, MAP_SIZE), margin=0.08))
        overview = self._map[1]
        left, top = self.size[0] - MAP_SIZE - 8, self.size[1] - MAP_SIZE - 8
        canvas.surface.blit(overview.surface, (left, top))
        self.pg.draw.rect(canvas.surface, TEXT, (left, top, MAP_SIZE, MAP_SIZE), 1)
        for x, y, colour in reversed(cars):  # the driven car on top
            px, py = overview.to_screen([[x, y]])[0]
            self.pg.draw.circle(canvas.surface, colour, (left + px, top + py), 4)

    def close(self) -> None:
        if self.window is not None:
            self.pg.display.quit()
            self.window = None
