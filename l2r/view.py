"""`l2r view`: watch logged episodes, or a run live, in Rerun.

    l2r view FILE.mcap [FILE ...] [--save out.rrd | --web]
    l2r view --live --run NAME [--connect tcp/HOST:PORT] [--save out.rrd | --web]

Episode files (from ``l2r.actors.episode_log``) play as one recording, one episode after the
other on the ``time`` timeline: the body drawn from the model's own shapes moving over the
ground and obstacles, each muscle a line along its path coloured by activation (blue at
rest, red fully active), and time series of reward, distance, pelvis height, activations and
forces. A camera task's episodes show the frames the policy saw, one image view per camera
field, beside their reward; a photo task's its images step by step (each query's and the goal)
beside the reward and the PSNR to the goal. Interrupted ``.mcap.part`` files play up to where
they stop.

``--live`` declares a viewer liveliness token, which tells actors to publish low-rate frames
of the episodes they are running, and draws those frames as they come: the runner's body, or a
camera task's frames, one image view per camera field and environment.

For other modules: ``write_recording(mcap_paths, rrd_path)`` converts episode files into a
``.rrd`` file (``l2r up`` uses it for the best evaluation episode, found by
``l2r.episodes.read.find_episode``).
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time
import urllib.parse
import uuid
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from l2r.config import (
    CommandParser, FilePath, StartupFailure, UsageError, load, run_command, setting, settings_parser,
)
from l2r.episodes.body import BodyModel, Shape, rotate
from l2r.episodes.read import Episode, read_episode
from l2r.protocol.session import DaemonSettings, configure_logging, wait_until_stopped

APP_ID = "l2r"
GROUND = "world/ground"  # the model's y-up frame, turned z-up under "world"
GAP_SECONDS = 0.5  # pause on the timeline between two episodes
GROUND_ROTATION = rr.Quaternion(xyzw=[np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)])  # +90 deg about x
CAMERA = f"{GROUND}/camera"  # follows the pelvis along the track; the 3D view looks through it
CAMERA_HEIGHT, CAMERA_DISTANCE = 1.0, 4.0  # m above the ground, and beside the track
IMAGES = "images"  # a camera task's frames: images/<observation field>, live images/<field>/actor<a>_env<e>


# ------------------------------------------------------------------------------ recordings


def blueprint(follow: bool = True, images: Sequence[str] = (), psnr: bool = False) -> rrb.Blueprint:
    """The layout: the runner in 3D (seen from its side through CAMERA, which moves with it, when
    ``follow``; live runners of many actors get the viewer's own camera), the episodes, and plots;
    or with ``images`` (the entities under IMAGES: a camera or photo task's fields, or live, each
    field of each environment, ``pixels/actor0_env1``) its frames, the episodes and the reward,
    and with ``psnr`` a photo task's PSNR to its goal."""
    reward = rrb.TimeSeriesView(name="reward", origin="/plots/reward")
    if images:
        scenes = [rrb.Spatial2DView(name=name, origin=f"/{IMAGES}/{name}") for name in images]
        plots = [reward, *([rrb.TimeSeriesView(name="PSNR to the goal (dB)", origin="/plots/psnr_db")] if psnr else [])]
    else:
        eye = rrb.EyeControls3D(tracking_entity=CAMERA) if follow else None
        scenes = [rrb.Spatial3DView(name="runner", origin="/world", eye_controls=eye)]
        plots = [
            reward,
            rrb.TimeSeriesView(name="distance and pelvis height (m)", contents=["/plots/distance/**", "/plots/pelvis_height/**"]),
            rrb.TimeSeriesView(name="muscle activation", origin="/plots/muscle_activation"),
            rrb.TimeSeriesView(name="muscle force (N)", origin="/plots/muscle_force"),
            rrb.TimeSeriesView(name="ligament and contact forces", contents=["/plots/ligament_force/**", "/plots/contact_force/**"]),
        ]
    return rrb.Blueprint(
        rrb.Horizontal(
            # (a grid: a live camera run may have dozens of environments to show)
            rrb.Vertical(rrb.Grid(*scenes), rrb.TextLogView(name="episodes", origin="/episodes"), row_shares=[5, 1]),
            rrb.Vertical(*plots),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(state="expanded"),
        collapse_panels=True,
    )


def new_recording(recording_id: str | None = None) -> rr.RecordingStream:
    return rr.RecordingStream(APP_ID, recording_id=recording_id or str(uuid.uuid4()))


def log_episodes(rec: rr.RecordingStream, episodes: Sequence[Episode], body: BodyModel | None = None) -> None:
    """Log episodes one after the other, drawn with ``body`` (default: the first file's; none for a
    camera task's)."""
    body = body or next((e.body for e in episodes if e.body is not None), None)
    if body is not None:
        log_body(rec, body)
    offset, step_offset = 0.0, 0
    for number, episode in enumerate(episodes):
        if len(episode) == 0:
            continue
        times = offset + episode.steps["time"]
        log_episode(rec, episode, body, number, times, step_offset + episode.steps["step"])
        offset = float(times[-1]) + GAP_SECONDS
        step_offset += int(episode.steps["step"][-1]) + 1


def log_body(rec: rr.RecordingStream, body: BodyModel) -> None:
    """Static shapes under each body's frame, the floor, and the series' names."""
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log(GROUND, rr.Transform3D(quaternion=GROUND_ROTATION), static=True)
    for name in body.bodies:
        _log_shapes(rec, f"{GROUND}/bodies/{name}/shape", [s for s in body.shapes if s.body == name])
    _log_shapes(rec, f"{GROUND}/floor", body.ground_shapes())
    # Right, up, back: in the ground frame (x along the track, y up) it looks at the track along -z.
    rec.log(CAMERA, rr.Pinhole(fov_y=0.9, aspect_ratio=1.6, camera_xyz=rr.ViewCoordinates.RUB,
                               image_plane_distance=0.05), static=True)
    rec.log("plots/muscle_activation", rr.SeriesLines(names=list(body.muscles)), static=True)
    rec.log("plots/muscle_force", rr.SeriesLines(names=list(body.muscles)), static=True)


def log_episode(
    rec: rr.RecordingStream, episode: Episode, body: BodyModel | None, number: int, times: np.ndarray, steps: np.ndarray
) -> None:
    index = [rr.TimeColumn("time", duration=times), rr.TimeColumn("step", sequence=steps)]
    rec.set_time("time", duration=float(times[0]))
    rec.set_time("step", sequence=int(steps[0]))
    describe = ", ".join(f"{k}={v}" for k, v in {**episode.episode, **episode.result}.items())
    rec.log("episodes", rr.TextLog(f"episode {number}: {episode.path.name} ({describe})"))
    s = episode.steps
    rec.send_columns("plots/reward", index, rr.Scalars.columns(scalars=s["reward"]))
    if is_photo(episode):
        rec.send_columns("plots/psnr_db", index, rr.Scalars.columns(scalars=s["psnr_db"]))
    for name, frames in episode.images.items():  # frame k is step k's; a cut file may end its frames sooner
        n, (height, width) = len(frames), frames.shape[2:]
        image_format = rr.components.ImageFormat(width=width, height=height, color_model="RGB", channel_datatype="U8")
        frame_index = [rr.TimeColumn("time", duration=times[:n]), rr.TimeColumn("step", sequence=steps[:n])]
        rec.send_columns(f"{IMAGES}/{name}", frame_index, rr.Image.columns(
            buffer=frames.transpose(0, 2, 3, 1).reshape(n, -1), format=[image_format] * n))  # fmt: skip
    if body is None:
        return
    obstacles = _obstacles(episode.episode.get("obstacles", ""))
    rec.log(f"{GROUND}/obstacles", rr.Ellipsoids3D(
        centers=[(x, y, 0.0) for x, y, _ in obstacles], half_sizes=[(r, r, r) for _, _, r in obstacles],
        colors=[(115, 90, 75)] * len(obstacles), fill_mode=rr.components.FillMode.Solid))  # fmt: skip
    for series, names in (("ligament_force", "ligaments"), ("contact_force", "contacts")):
        if episode.names.get(names):  # one plot line per ligament and foot sphere, by the model's name
            rec.log(f"plots/{series}", rr.SeriesLines(names=list(episode.names[names])), static=True)
    for name in ("distance", "pelvis_height"):
        rec.send_columns(f"plots/{name}", index, rr.Scalars.columns(scalars=s[name]))
    for name in ("muscle_activation", "muscle_force", "ligament_force"):
        if s[name].size:
            rec.send_columns(f"plots/{name}", index, rr.Scalars.columns(scalars=s[name]))
    if s["contact_force"].size:
        per_sphere = np.linalg.norm(s["contact_force"].reshape(len(times), -1, 3), axis=2)
        rec.send_columns("plots/contact_force", index, rr.Scalars.columns(scalars=per_sphere))

    if not episode.pos.size:
        return
    bodies = episode.names.get("bodies") or body.bodies
    for i, name in enumerate(bodies):
        quat = episode.quat[:, i][:, [1, 2, 3, 0]]
        rec.send_columns(f"{GROUND}/bodies/{name}", index,
                         rr.Transform3D.columns(translation=episode.pos[:, i], quaternion=quat))  # fmt: skip
    pelvis_x = episode.pos[:, list(bodies).index("pelvis"), 0]
    eye = np.column_stack([pelvis_x, np.full_like(pelvis_x, CAMERA_HEIGHT), np.full_like(pelvis_x, CAMERA_DISTANCE)])
    rec.send_columns(CAMERA, index, rr.Transform3D.columns(translation=eye))
    if s["muscle_activation"].size and body.paths:
        points = body.muscle_points(episode.pos, episode.quat)
        strips = [points[m][t] for t in range(len(times)) for m in range(len(points))]
        colors = activation_colors(s["muscle_activation"][:, : len(points)]).reshape(-1, 3)
        rec.send_columns(f"{GROUND}/muscles", index, rr.LineStrips3D.columns(
            strips=strips, colors=colors, radii=np.full(len(strips), 0.008)).partition([len(points)] * len(times)))  # fmt: skip


def activation_colors(activation: np.ndarray) -> np.ndarray:
    """RGB per activation in [0, 1]: blue at rest to red fully active."""
    a = np.clip(activation, 0.0, 1.0)[..., None]
    return ((1 - a) * np.array([60, 90, 220]) + a * np.array([230, 40, 30])).astype(np.uint8)


def _log_shapes(rec: rr.RecordingStream, path: str, shapes: list[Shape]) -> None:
    def pose(s: Shape) -> tuple[list, list]:
        return list(s.pos), [*s.quat[1:], s.quat[0]]

    def color(s: Shape) -> list[int]:
        return [int(255 * c) for c in s.rgba]

    capsules = [s for s in shapes if s.kind == "capsule"]
    if capsules:  # Rerun's capsule starts at its translation and runs along +z; the model's is centred
        starts = [np.asarray(s.pos) - rotate(np.asarray(s.quat), np.array([0.0, 0.0, s.size[1]])) for s in capsules]
        rec.log(f"{path}/capsules", rr.Capsules3D(
            lengths=[2 * s.size[1] for s in capsules], radii=[s.size[0] for s in capsules], translations=starts,
            quaternions=[pose(s)[1] for s in capsules], colors=[color(s) for s in capsules]), static=True)  # fmt: skip
    cylinders = [s for s in shapes if s.kind == "cylinder"]
    if cylinders:
        rec.log(f"{path}/cylinders", rr.Cylinders3D(
            lengths=[2 * s.size[1] for s in cylinders], radii=[s.size[0] for s in cylinders],
            centers=[pose(s)[0] for s in cylinders], quaternions=[pose(s)[1] for s in cylinders],
            colors=[color(s) for s in cylinders]), static=True)  # fmt: skip
    round_ = [s for s in shapes if s.kind in ("sphere", "ellipsoid")]
    if round_:
        rec.log(f"{path}/ellipsoids", rr.Ellipsoids3D(
            half_sizes=[(s.size * 3)[:3] for s in round_], centers=[pose(s)[0] for s in round_],
            quaternions=[pose(s)[1] for s in round_], colors=[color(s) for s in round_],
            fill_mode=rr.components.FillMode.Solid), static=True)  # fmt: skip
    boxes = [s for s in shapes if s.kind == "box"]
    if boxes:
        rec.log(f"{path}/boxes", rr.Boxes3D(
            half_sizes=[s.size for s in boxes], centers=[pose(s)[0] for s in boxes],
            quaternions=[pose(s)[1] for s in boxes], colors=[color(s) for s in boxes],
            fill_mode=rr.components.FillMode.Solid), static=True)  # fmt: skip


def image_fields(episodes: Sequence[Episode]) -> list[str]:
    """The camera fields of these episodes, in the order they first come."""
    return list(dict.fromkeys(name for episode in episodes for name in episode.images))


def is_photo(episode: Episode) -> bool:
    """Whether the episode is a photo task's: its result holds the PSNR it ended at."""
    return "psnr_db" in episode.result


def _obstacles(text: str) -> list[tuple[float, float, float]]:
    return [tuple(float(v) for v in item.split(",")) for item in text.split(";") if item]


def write_recording(mcap_paths: Sequence[str | Path], rrd_path: str | Path) -> Path:
    """Convert episode files into one Rerun recording file (episodes in the given order)."""
    episodes = [read_episode(p) for p in mcap_paths]
    rec = new_recording()
    rec.save(str(rrd_path), default_blueprint=blueprint(images=image_fields(episodes),
                                                       psnr=any(map(is_photo, episodes))))
    log_episodes(rec, episodes)
    rec.flush()
    rec.disconnect()
    return Path(rrd_path)


# ------------------------------------------------------------------------------------ live


def watch_live(rec: rr.RecordingStream, conf, run: str, duration: float | None) -> int:
    """Draw the frames actors publish while this viewer's liveliness token exists: one runner
    per actor environment, under ``world/ground/actor<a>/env<e>``, or of a camera task one image
    per camera field and environment, under ``images/<field>/actor<a>_env<e>``."""
    import zenoh

    from l2r.protocol.keys import Keys
    from l2r.protocol.messages import Frame, ProtocolError, decode
    from l2r.protocol.session import Rejections
    from l2r.sim.model import load_model

    body = BodyModel.from_model(load_model())
    log_episodes(rec, [], body)
    keys = Keys(run)
    seen: set[tuple[int, int]] = set()
    image_views: list[str] = []  # images/<these>, one view each in the layout
    lock = threading.Lock()
    rejections = Rejections(logging.getLogger("l2r.view"))
    frames = 0

    def on_frame(sample: zenoh.Sample) -> None:
        nonlocal frames
        try:
            frame = decode(sample.payload, Frame)
        except ProtocolError as e:
            rejections.add(e, str(sample.key_expr))
            return
        root = f"{GROUND}/actor{frame.actor_id}/env{frame.env_id}"
        where = f"actor{frame.actor_id}_env{frame.env_id}"
        with lock:
            frames += 1
            if "body_pos" in frame.arrays and (frame.actor_id, frame.env_id) not in seen:
                seen.add((frame.actor_id, frame.env_id))
                for name in body.bodies:
                    _log_shapes(rec, f"{root}/{name}/shape", [s for s in body.shapes if s.body == name])
            new_views = [f"{name}/{where}" for name in frame.images or () if f"{name}/{where}" not in image_views]
            if new_views:  # a camera task's field or environment not drawn yet: a view of its own
                image_views.extend(new_views)
                rec.send_blueprint(blueprint(follow=False, images=image_views))
        log_frame(rec, body, frame, root, where)

    # Handled here, not left to KeyboardInterrupt: a process started in the background by a shell
    # inherits SIGINT ignored, and Python then never raises it; SIGTERM stops it the same way.
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    with zenoh.open(conf) as session:
        subscriber = session.declare_subscriber(keys.all_frames, on_frame)  # before the token asks for frames
        token = session.liveliness().declare_token(keys.alive("viewer", uuid.uuid4().hex[:12]))
        print(f"l2r view: watching run {run!r} (frames on {keys.all_frames}); Ctrl-C stops", file=sys.stderr)
        wait_until_stopped(stop, duration)
        subscriber.undeclare()
        token.undeclare()
    for sig, handler in previous.items():
        signal.signal(sig, handler)
    rejected = ", ".join(f"{n} {reason}" for reason, n in rejections.by_reason.items())
    print(f"l2r view: {frames} frames drawn, {rejections.total} rejected{f' ({rejected})' if rejected else ''}",
          file=sys.stderr)
    return 0


def log_frame(rec: rr.RecordingStream, body: BodyModel, frame, root: str, where: str) -> None:
    """One live frame (``l2r.episodes.live.frame``): poses, muscles, camera frames, reward and distance."""
    arrays = frame.arrays
    rec.set_time("wall", timestamp=time.time())
    rec.set_time("step", sequence=frame.step)
    if "body_pos" in arrays and "body_quat" in arrays:
        pos, quat = np.asarray(arrays["body_pos"], float)[1:], np.asarray(arrays["body_quat"], float)[1:]
        for i, name in enumerate(body.bodies):
            rec.log(f"{root}/{name}", rr.Transform3D(translation=pos[i], quaternion=[*quat[i, 1:], quat[i, 0]]))
        if "muscle_activation" in arrays and body.paths:
            points = body.muscle_points(pos, quat)
            colors = activation_colors(np.asarray(arrays["muscle_activation"])[: len(points)])
            rec.log(f"{root}/muscles", rr.LineStrips3D(points, colors=colors, radii=0.008))
    for name, rows in (frame.images or {}).items():  # (1, 3, H, W): channels last for Rerun
        rec.log(f"{IMAGES}/{name}/{where}", rr.Image(rows[0].transpose(1, 2, 0), color_model="RGB"))
    for name, value in frame.values.items():
        rec.log(f"plots/{name}/{where}", rr.Scalars(float(value)))


# ------------------------------------------------------------------------------------- cli


EPISODES, OUTPUT, LIVE = "episodes", "output", "live"


class ViewSettings(DaemonSettings):
    files: list[FilePath] = setting([], "episode files (.mcap, or interrupted .mcap.part), or directories of them",
                                    group=EPISODES, positional=True, metavar="FILE")
    save: FilePath | None = setting(None, "write a Rerun file instead of opening a viewer", group=OUTPUT,
                                    metavar="OUT.rrd")
    web: bool = setting(False, "serve the web viewer (for a machine without a screen) and print the URL that opens "
                        "it on the recording", group=OUTPUT)
    web_port: int = setting(9090, "with --web: port of the web viewer", group=OUTPUT, ge=1, le=65535)
    grpc_port: int = setting(9876, "with --web: port of the recording's gRPC server, which the web viewer reads",
                             group=OUTPUT, ge=1, le=65535)
    live: bool = setting(False, "watch the episodes a run's actors are running now", group=LIVE)
    duration: float | None = setting(None, "with --live: stop after this many seconds (default: until Ctrl-C)",
                                     group=LIVE, gt=0)

    def check(self) -> None:
        if self.save and self.web:
            raise UsageError("--save and --web exclude each other")
        if self.live == bool(self.files):
            raise UsageError("give episode files, or --live (with --run) to watch a running job")


def build_parser() -> CommandParser:
    return settings_parser(
        ViewSettings, "l2r view", "Watch logged episodes (one after the other), or a run's actors live, in Rerun.",
        "examples:\n  l2r view runs/exp1/episodes/*-eval.mcap\n  l2r view runs/exp1/episodes --save all.rrd\n"
        "  l2r view --live --run exp1 --connect tcp/127.0.0.1:7447 --web")


def cli(argv: list[str] | None = None) -> int:
    return run_command("l2r view", lambda: view(load(ViewSettings, build_parser(), argv)))


def serve_web(rec: rr.RecordingStream, web_port: int, grpc_port: int, blueprint_: rrb.Blueprint) -> str:
    """Serve ``rec`` over gRPC and the web viewer over HTTP; the URL that opens the viewer on the recording
    (the viewer's own address alone opens its welcome page)."""
    try:
        grpc_url = rec.serve_grpc(grpc_port=grpc_port, default_blueprint=blueprint_)
        rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=grpc_url)
    except RuntimeError as e:  # a port in use
        raise StartupFailure(f"cannot serve the web viewer: {str(e).splitlines()[0]}") from None
    return f"http://localhost:{web_port}/?url={urllib.parse.quote(grpc_url, safe='')}"


def view(s: ViewSettings) -> int:
    configure_logging(s.log_level)
    files = [f for p in s.files for f in (sorted(p.glob("*.mcap")) if p.is_dir() else [p])]
    if s.files and not files:
        raise UsageError(f"no .mcap files in {', '.join(map(str, s.files))}")
    missing = [str(p) for p in files if not p.is_file()]
    if missing:
        raise UsageError(f"no such file: {', '.join(missing)}")
    headless = sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    if headless and not (s.save or s.web):
        raise UsageError("no screen here (DISPLAY is not set): use --save FILE.rrd, or --web to serve the web viewer")

    episodes = []
    for path in files:
        try:
            episodes.append(read_episode(path))
        except (ValueError, OSError) as e:
            print(f"l2r view: skipping {path}: {e}", file=sys.stderr)
        else:
            episode = episodes[-1]
            state = "" if episode.complete else " (interrupted: shown up to where it stops)"
            print(f"l2r view: {path.name}: {len(episode)} steps{state}", file=sys.stderr)
    if files and not episodes:
        raise StartupFailure("none of the files is a readable episode")

    layout = blueprint(follow=not s.live, images=image_fields(episodes), psnr=any(map(is_photo, episodes)))
    rec = new_recording()
    if s.save:
        rec.save(str(s.save), default_blueprint=layout)
    elif s.web:
        url = serve_web(rec, s.web_port, s.grpc_port, layout)
        print(f"l2r view: open {url} (Ctrl-C stops)", file=sys.stderr, flush=True)
    else:
        # The viewer binary comes with rerun-sdk next to this Python, which may not be on PATH.
        os.environ["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])
        try:
            rec.spawn(default_blueprint=layout)
        except RuntimeError as e:
            raise StartupFailure(f"cannot start the Rerun viewer ({str(e).splitlines()[0]}); use --save FILE.rrd, "
                                 "or --web on a machine without a screen") from None

    if s.live:
        status = watch_live(rec, s.zenoh_session_config(), s.run, s.duration)
    else:
        log_episodes(rec, episodes)
        status = 0
    try:
        rec.flush()
    except RuntimeError as e:  # the viewer went away (closed, or could not open a window)
        print(f"l2r view: the Rerun viewer is gone: {e}", file=sys.stderr)
        return 1
    if s.save:
        print(f"l2r view: wrote {s.save}", file=sys.stderr)
    elif s.web and not s.live:
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
    return status


if __name__ == "__main__":
    sys.exit(cli())
