"""`l2r view`: watch logged episodes, or a run live, in Rerun.

    l2r view FILE.mcap [FILE ...] [--save out.rrd | --web]
    l2r view --live --run NAME [--connect tcp/HOST:PORT] [--save out.rrd | --web]

Episode files (from ``l2r.actors.episode_log``) play as one recording, one episode after the
other on the ``time`` timeline: the body drawn from the model's own shapes moving over the
ground and obstacles, each muscle a line along its path coloured by activation (blue at
rest, red fully active), and time series of reward, distance, pelvis height, activations and
forces. Interrupted ``.mcap.part`` files play up to where they stop.

``--live`` declares a viewer liveliness token, which tells actors to publish low-rate frames
of the episodes they are running, and draws those frames as they come.

For other modules: ``write_recording(mcap_paths, rrd_path)`` converts episode files into a
``.rrd`` file (``l2r up`` uses it for the best evaluation episode), and
``find_episode(directory, kind=..., seed=...)`` finds the episode file with that metadata.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import uuid
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from mcap.reader import SeekingReader
from mcap.records import Metadata

from l2r.episodes.body import BodyModel, Shape, rotate
from l2r.episodes.read import Episode, iter_records, read_episode

APP_ID = "l2r"
GROUND = "world/ground"  # the model's y-up frame, turned z-up under "world"
GAP_SECONDS = 0.5  # pause on the timeline between two episodes
GROUND_ROTATION = rr.Quaternion(xyzw=[np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5)])  # +90 deg about x


# ------------------------------------------------------------------------------ recordings


def blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(name="runner", origin="/world"),
                rrb.TextLogView(name="episodes", origin="/episodes"),
                row_shares=[5, 1],
            ),
            rrb.Vertical(
                rrb.TimeSeriesView(name="reward", origin="/plots/reward"),
                rrb.TimeSeriesView(name="distance and pelvis height (m)", contents=["/plots/distance/**", "/plots/pelvis_height/**"]),
                rrb.TimeSeriesView(name="muscle activation", origin="/plots/muscle_activation"),
                rrb.TimeSeriesView(name="muscle force (N)", origin="/plots/muscle_force"),
                rrb.TimeSeriesView(name="ligament and contact forces", contents=["/plots/ligament_force/**", "/plots/contact_force/**"]),
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(state="expanded"),
        collapse_panels=True,
    )


def new_recording(recording_id: str | None = None) -> rr.RecordingStream:
    return rr.RecordingStream(APP_ID, recording_id=recording_id or str(uuid.uuid4()))


def log_episodes(rec: rr.RecordingStream, episodes: Sequence[Episode], body: BodyModel | None = None) -> None:
    """Log episodes one after the other, drawn with ``body`` (default: the first file's)."""
    rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    rec.log(GROUND, rr.Transform3D(quaternion=GROUND_ROTATION), static=True)
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
    for name in body.bodies:
        _log_shapes(rec, f"{GROUND}/bodies/{name}/shape", [s for s in body.shapes if s.body == name])
    _log_shapes(rec, f"{GROUND}/floor", body.ground_shapes())
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
    obstacles = _obstacles(episode.episode.get("obstacles", ""))
    rec.log(f"{GROUND}/obstacles", rr.Ellipsoids3D(
        centers=[(x, y, 0.0) for x, y, _ in obstacles], half_sizes=[(r, r, r) for _, _, r in obstacles],
        colors=[(115, 90, 75)] * len(obstacles), fill_mode=rr.components.FillMode.Solid))  # fmt: skip
    s = episode.steps
    for name in ("reward", "distance", "pelvis_height"):
        rec.send_columns(f"plots/{name}", index, rr.Scalars.columns(scalars=s[name]))
    for name in ("muscle_activation", "muscle_force", "ligament_force"):
        if s[name].size:
            rec.send_columns(f"plots/{name}", index, rr.Scalars.columns(scalars=s[name]))
    if s["contact_force"].size:
        per_sphere = np.linalg.norm(s["contact_force"].reshape(len(times), -1, 3), axis=2)
        rec.send_columns("plots/contact_force", index, rr.Scalars.columns(scalars=per_sphere))

    if body is None or not episode.pos.size:
        return
    for i, name in enumerate(episode.names.get("bodies") or body.bodies):
        quat = episode.quat[:, i][:, [1, 2, 3, 0]]
        rec.send_columns(f"{GROUND}/bodies/{name}", index,
                         rr.Transform3D.columns(translation=episode.pos[:, i], quaternion=quat))  # fmt: skip
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


def _obstacles(text: str) -> list[tuple[float, float, float]]:
    return [tuple(float(v) for v in item.split(",")) for item in text.split(";") if item]


def write_recording(mcap_paths: Sequence[str | Path], rrd_path: str | Path) -> Path:
    """Convert episode files into one Rerun recording file (episodes in the given order)."""
    rec = new_recording()
    rec.save(str(rrd_path), default_blueprint=blueprint())
    log_episodes(rec, [read_episode(p) for p in mcap_paths])
    rec.flush()
    rec.disconnect()
    return Path(rrd_path)


def find_episode(directory: str | Path, **episode: str | int) -> Path | None:
    """The first episode file in ``directory`` whose "episode" metadata holds every item of
    ``episode`` (``kind="eval", actor=1, seed=0, policy_version=12``), or None."""
    wanted = {name: str(value) for name, value in episode.items()}
    for path in sorted(Path(directory).glob("*.mcap")):
        meta = episode_metadata(path).get("episode", {})
        if all(meta.get(name) == value for name, value in wanted.items()):
            return path
    return None


def episode_metadata(path: str | Path) -> dict[str, dict[str, str]]:
    """The metadata records of an episode file, by name: read through the summary's index in
    a complete file, by a scan in a damaged one."""
    try:
        with open(path, "rb") as f:
            return {m.name: dict(m.metadata) for m in SeekingReader(f).iter_metadata()}
    except Exception:  # no usable summary: scan what can be read
        return {r.name: dict(r.metadata) for r in iter_records(path) if isinstance(r, Metadata)}


# ------------------------------------------------------------------------------------ live


def watch_live(rec: rr.RecordingStream, conf, run: str, duration: float | None) -> int:
    """Draw the frames actors publish while this viewer's liveliness token exists: one runner
    per actor environment, under ``world/ground/actor<a>/env<e>``."""
    import zenoh

    from l2r.protocol.keys import Keys
    from l2r.protocol.messages import Frame, ProtocolError, decode
    from l2r.sim.model import load_model

    body = BodyModel.from_model(load_model())
    log_episodes(rec, [], body)
    keys = Keys(run)
    seen: set[tuple[int, int]] = set()
    counts = {"frames": 0, "rejected": 0}

    def on_frame(sample: zenoh.Sample) -> None:
        try:
            frame = decode(sample.payload, Frame)
        except ProtocolError as e:
            counts["rejected"] += 1
            if counts["rejected"] <= 3:
                print(f"l2r view: rejected a frame from {sample.key_expr}: {e}", file=sys.stderr)
            return
        root = f"{GROUND}/actor{frame.actor_id}/env{frame.env_id}"
        if (frame.actor_id, frame.env_id) not in seen:
            seen.add((frame.actor_id, frame.env_id))
            for name in body.bodies:
                _log_shapes(rec, f"{root}/{name}/shape", [s for s in body.shapes if s.body == name])
        log_frame(rec, body, frame, root)
        counts["frames"] += 1

    with zenoh.open(conf) as session:
        subscriber = session.declare_subscriber(keys.all_frames, on_frame)  # before the token asks for frames
        token = session.liveliness().declare_token(keys.alive("viewer", uuid.uuid4().hex[:12]))
        print(f"l2r view: watching run {run!r} (frames on {keys.all_frames}); Ctrl-C stops", file=sys.stderr)
        deadline = None if duration is None else time.monotonic() + duration
        try:
            while deadline is None or time.monotonic() < deadline:
                time.sleep(0.1)
        except KeyboardInterrupt:
            pass
        subscriber.undeclare()
        token.undeclare()
    print(f"l2r view: {counts['frames']} frames from {len(seen)} environment(s) drawn", file=sys.stderr)
    return 0


def log_frame(rec: rr.RecordingStream, body: BodyModel, frame, root: str) -> None:
    """One live frame (``l2r.episodes.live.frame``): poses, muscles, reward and distance."""
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
    where = f"actor{frame.actor_id}_env{frame.env_id}"
    for name, value in frame.values.items():
        rec.log(f"plots/{name}/{where}", rr.Scalars(float(value)))


# ------------------------------------------------------------------------------------- cli


def cli(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="l2r view", description="Watch logged episodes (one after the other), or a run's actors live, in Rerun.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n  l2r view runs/exp1/episodes/*-eval.mcap\n  l2r view runs/exp1/episodes --save all.rrd\n"
               "  l2r view --live --run exp1 --connect tcp/127.0.0.1:7447 --web",
    )  # fmt: skip
    parser.add_argument("files", nargs="*", type=Path,
                        help="episode files (.mcap, or interrupted .mcap.part), or directories of them")
    out = parser.add_mutually_exclusive_group()
    out.add_argument("--save", type=Path, metavar="OUT.rrd", help="write a Rerun file instead of opening a viewer")
    out.add_argument("--web", action="store_true", help="serve the web viewer (for a machine without a screen)")
    parser.add_argument("--web-port", type=int, default=9090, help="web viewer port with --web (default: %(default)s)")
    live = parser.add_argument_group("live")
    live.add_argument("--live", action="store_true", help="watch the episodes a run's actors are running now")
    live.add_argument("--duration", type=float, help="with --live: stop after this many seconds (default: until Ctrl-C)")
    from l2r.protocol.session import add_daemon_arguments, config_from_args, configure_logging, parse_daemon_args

    add_daemon_arguments(parser)
    args = parse_daemon_args(parser, argv)
    configure_logging(args.log_level)
    if args.live == bool(args.files):
        parser.error("give episode files, or --live (with --run) to watch a running job")
    given = args.files
    args.files = [f for p in given for f in (sorted(p.glob("*.mcap")) if p.is_dir() else [p])]
    if given and not args.files:
        parser.error(f"no .mcap files in {', '.join(map(str, given))}")
    missing = [str(p) for p in args.files if not p.is_file()]
    if missing:
        parser.error(f"no such file: {', '.join(missing)}")
    headless = sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
    if headless and not (args.save or args.web):
        parser.error("no screen here (DISPLAY is not set): use --save FILE.rrd, or --web to serve the web viewer")

    episodes = []
    for path in args.files:
        try:
            episodes.append(read_episode(path))
        except (ValueError, OSError) as e:
            print(f"l2r view: skipping {path}: {e}", file=sys.stderr)
        else:
            episode = episodes[-1]
            state = "" if episode.complete else " (interrupted: shown up to where it stops)"
            print(f"l2r view: {path.name}: {len(episode)} steps{state}", file=sys.stderr)
    if args.files and not episodes:
        print("l2r view: none of the files is a readable episode", file=sys.stderr)
        return 1

    rec = new_recording()
    if args.save:
        rec.save(str(args.save), default_blueprint=blueprint())
    elif args.web:
        url = rec.serve_grpc(default_blueprint=blueprint())
        rr.serve_web_viewer(web_port=args.web_port, open_browser=False, connect_to=url)
        print(f"l2r view: web viewer on http://localhost:{args.web_port} (Ctrl-C stops)", file=sys.stderr)
    else:
        # The viewer binary comes with rerun-sdk next to this Python, which may not be on PATH.
        os.environ["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])
        try:
            rec.spawn(default_blueprint=blueprint())
        except RuntimeError as e:
            print(f"l2r view: cannot start the Rerun viewer ({str(e).splitlines()[0]}); "
                  "use --save FILE.rrd, or --web on a machine without a screen", file=sys.stderr)  # fmt: skip
            return 1

    if args.live:
        status = watch_live(rec, config_from_args(args), args.run, args.duration)
    else:
        log_episodes(rec, episodes)
        status = 0
    try:
        rec.flush()
    except RuntimeError as e:  # the viewer went away (closed, or could not open a window)
        print(f"l2r view: the Rerun viewer is gone: {e}", file=sys.stderr)
        return 1
    if args.save:
        print(f"l2r view: wrote {args.save}", file=sys.stderr)
    elif args.web and not args.live:
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass
    return status


if __name__ == "__main__":
    sys.exit(cli())
