"""`l2r photo`: tune a photo's finishing towards a goal image, compare tuners on held-out photos,
and compare enhancers of degraded held-out photos.

    l2r photo tune INPUT --goal TARGET --out OUT.png [--checkpoint CK | --optimizer cmaes --queries N]
    l2r photo compare [FIVEK_FOLDER] [--checkpoint CK] [--photos N] [--json]
    l2r photo enhance [FIVEK_FOLDER] [--checkpoint CK] [--photos N] [--json]
    l2r photo pretrain --out CK [--rounds N] [--episodes N] [--updates N] [--workers N] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from l2r.config import CommandParser
from l2r.photo import enhance, photos, pretrain, tune
from l2r.photo.env import GOAL_SETS, PhotoEnhanceEnv, psnr_db
from l2r.photo.pipeline import NAMES, finish, params_from_actions

OPTIMIZERS = {"cmaes": tune.cmaes, "random": tune.random_search}
DEFAULT_QUERIES = 200


class PhotoError(Exception):
    """What makes a command stop: its message is the one line it prints."""


def build_parser() -> argparse.ArgumentParser:
    p = CommandParser(prog="l2r photo",
                      description="Photo finishing with the nine parameters of RLPixTuner's pipeline (exposure, "
                                  "white balance, saturation, contrast, highlights, shadows, sharpening; "
                                  "docs/photo.md): tune one photo towards a goal image, compare the tuners on the "
                                  "held-out photos, or compare enhancers of degraded held-out photos. A query is one "
                                  "run of the pipeline on the 256 x 256 working image; PSNR and SSIM are to the goal.")
    commands = p.add_subparsers(dest="command", required=True, metavar="{tune,compare,enhance,pretrain}")
    t = commands.add_parser("tune", help="find the parameters that turn INPUT into TARGET and write the finished image",
                            description="Find the parameters that turn INPUT into the look of TARGET (the same "
                                        "photo, finished otherwise), with a trained policy (--checkpoint, 10 "
                                        "queries) or an optimiser (--optimizer, --queries), on both resized to the "
                                        "256 x 256 working image; then finish INPUT at full resolution with them, "
                                        "write it to --out, and print the PSNR / SSIM reached per query and the "
                                        "nine parameters.")
    t.add_argument("input", metavar="INPUT", type=Path, help="the photo to finish (8- or 16-bit RGB: PNG, JPEG, TIFF)")
    t.add_argument("--goal", metavar="TARGET", type=Path, required=True,
                   help="the look to reach: the same photo finished otherwise, of INPUT's size")
    t.add_argument("--out", metavar="OUT.png", type=Path, required=True, help="where the finished photo goes (8-bit)")
    t.add_argument("--checkpoint", metavar="CK", type=Path,
                   help="tune with this policy of l2r/PhotoTune-v0 (a checkpoint file, best.pt, or an `l2r up` run "
                        "directory): its deterministic actions, one query per step")
    t.add_argument("--optimizer", choices=tuple(OPTIMIZERS),
                   help="without --checkpoint: CMA-ES (the default) or uniform random search, the best query kept")
    t.add_argument("--queries", type=int, metavar="N",
                   help=f"without --checkpoint: the optimiser's budget (default: {DEFAULT_QUERIES})")
    add_common(t)
    c = commands.add_parser("compare", help="the policy against random search and CMA-ES on the held-out photos",
                            description="On held-out problems as l2r/PhotoTune-v0 poses them (a crop of a test "
                                        "photo and a goal made with hidden random parameters: RLPixTuner's "
                                        "FiveK-Random; or, with --goals looks, another test scene's look), the mean "
                                        "PSNR and SSIM to the goal of the untouched input, of random search and "
                                        "CMA-ES at each budget, and of the policy at 10 queries when --checkpoint "
                                        "is given; a table, or one JSON line.")
    add_held_out(c, "also run this policy of l2r/PhotoTune-v0")
    c.add_argument("--budgets", default=",".join(map(str, tune.BUDGETS)), metavar="N,N,...",
                   help=f"the optimisers' query budgets (default: {','.join(map(str, tune.BUDGETS))})")
    c.add_argument("--goals", choices=GOAL_SETS, default="random",
                   help="random: the crop finished with hidden random parameters, which an exact answer reaches; "
                        "looks: the crop with the colour statistics of a crop of another test scene (Reinhard's "
                        "colour transfer in CIELAB), a grade the pipeline can only approach (default: random)")
    add_common(c)
    e = commands.add_parser("enhance", help="the enhancer's policy against automatic levels and histogram "
                                            "equalisation on degraded held-out photos",
                            description="On held-out problems as l2r/PhotoEnhance-v0 poses them (a crop of a test "
                                        "photo degraded by the pipeline with hidden random parameters), the mean "
                                        "PSNR and SSIM to the original crop of the degraded input, of scikit-image's "
                                        "automatic levels (each channel's 2nd-98th percentile stretched to [0, 1]) "
                                        "and histogram equalisation (per channel), and of the policy's edits at 10 "
                                        "queries when --checkpoint is given; a table, or one JSON line.")
    add_held_out(e, "also run this policy of l2r/PhotoEnhance-v0 or l2r/PhotoEnhanceStats-v0 (a checkpoint file, "
                    "best.pt, or an `l2r up` run directory)")
    add_common(e)
    defaults = pretrain.PretrainConfig()
    w = commands.add_parser("pretrain", help="learn a tuner from the hidden parameters of random goals (a warm start)",
                            description="Learn the tuner's policy with supervision: on the task's random goals, "
                                        "whose hidden parameters are the answer, its actions are regressed onto them "
                                        "over episodes whose queries are the answer blurred by noise (and, with "
                                        "--rounds above 1, over the policy's own noisy queries: DAgger); then write it "
                                        "as a policy checkpoint that `l2r photo compare` and `tune` run and `l2r up "
                                        "--algo td3 --init-from` trains on: about 26 minutes of one CPU core (40 beside "
                                        "other work on 2 cores), where TD3 took 34 on a busy core to a tuner 9 dB "
                                        "worse (docs/photo.md).")
    w.add_argument("--out", metavar="CK", type=Path, required=True, help="where the policy checkpoint goes")
    w.add_argument("--env-id", choices=tune.TUNE_IDS, default=defaults.env_id,
                   help=f"the task whose observations the policy takes (default: {defaults.env_id}, the "
                        f"statistics of both images and the two compared pixel for pixel; l2r/PhotoTuneStats-v0, the "
                        f"statistics alone, did 0.8 dB better on other scenes' looks and 2.3 worse on random edits "
                        f"(3,000 episodes each); "
                        f"l2r/PhotoTune-v0's images train through convolutions, slowly on a CPU)")
    w.add_argument("--rounds", type=int, default=defaults.rounds,
                   help=f"rounds of episodes; each after the first adds half as many of the policy's own noisy "
                        f"queries (DAgger), which cost 2.0 dB on held-out random edits (default: {defaults.rounds})")
    w.add_argument("--episodes", type=int, default=defaults.episodes,
                   help=f"episodes of the first round, 10 queries each; each later round adds half as many "
                        f"(default: {defaults.episodes})")
    w.add_argument("--updates", type=int, default=defaults.updates,
                   help=f"Adam steps a round, batches of {defaults.batch_size} (default: {defaults.updates})")
    w.add_argument("--lr-schedule", choices=pretrain.LR_SCHEDULES, default=defaults.lr_schedule,
                   help=f"the Adam steps' learning rate, {defaults.lr} throughout a round (constant) or falling "
                        f"to 0 along half a cosine (default: %(default)s)")
    w.add_argument("--workers", type=int, default=defaults.workers,
                   help="processes that play the episodes, most of the warm start's time on one core; the "
                        "result is the same whatever their number (default: %(default)s)")
    w.add_argument("--eval-episodes", type=int, default=defaults.eval_episodes,
                   help=f"deterministic episodes on the training photos that judge the result (default: "
                        f"{defaults.eval_episodes}); the held-out photos are `l2r photo compare`'s")
    w.add_argument("--source-variety", type=float, default=defaults.source_variety, metavar="FRACTION",
                   help="each training crop flipped at random and finished with random actions within ± FRACTION "
                        "before its hidden edit, so that the few training photos show many colourings (0: off; "
                        "default: %(default)s, which held the three seeds' held-out results within 0.5 dB)")
    w.add_argument("--residual", action="store_true",
                   help="each query a change to the last one's parameters (a residual head: a query nearly right "
                        "stays so); TD3 trains on from it with --learner-arg=--residual-from=N, N as the run prints")
    add_common(w)
    return p


def add_held_out(p: argparse.ArgumentParser, checkpoint_help: str) -> None:
    """The arguments of a command run on held-out problems: where they come from, how many, and a policy."""
    p.add_argument("folder", metavar="FIVEK_FOLDER", type=Path, nargs="?",
                   help="crop the test split of a MIT-Adobe FiveK folder's inputs (input/ beside expertC_gt/) "
                        "instead of l2r's held-out photos (chelsea, coffee, grace_hopper)")
    p.add_argument("--checkpoint", metavar="CK", type=Path, help=checkpoint_help)
    p.add_argument("--photos", type=int, default=12, metavar="N",
                   help="problems, on the task's seeds --seed, --seed + 1, ... (default: 12)")


def add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=int, default=0, help="seed of the problems (and of the optimisers, where they run) (default: 0)")
    p.add_argument("--json", action="store_true", help="print one JSON line instead of text")


def load_policy(path: Path):
    import torch

    from l2r.learner.checkpoint import CheckpointError, load_checkpoint

    torch.set_num_threads(1)
    try:
        return load_checkpoint(path).policy()
    except CheckpointError as e:
        raise PhotoError(str(e)) from None


def read_float(path: Path) -> np.ndarray:
    """An image file as float32 [3, H, W] in [0, 1]."""
    if not path.is_file():
        raise PhotoError(f"{path}: no such file")
    try:
        image = photos.read_image(path)
    except (OSError, ValueError) as e:
        raise PhotoError(f"{path}: cannot read it as an RGB image ({e})") from None
    return (image / np.float32(np.iinfo(image.dtype).max)).astype(np.float32)


def working(image: np.ndarray) -> np.ndarray:
    """A [3, H, W] image resized to the working image, [3, 256, 256] (anti-aliased)."""
    from skimage.transform import resize

    side = photos.WORKING_SIZE
    return resize(image.transpose(1, 2, 0), (side, side), anti_aliasing=True).transpose(2, 0, 1).astype(np.float32)


def run_tune(args: argparse.Namespace) -> dict:
    if args.checkpoint is not None and (args.optimizer or args.queries):
        raise PhotoError("--checkpoint tunes with the policy's own queries: no --optimizer or --queries with it")
    if args.queries is not None and args.queries < 1:
        raise PhotoError("--queries must be at least 1")
    source, goal = read_float(args.input), read_float(args.goal)
    if source.shape != goal.shape:
        raise PhotoError(f"{args.input} is {source.shape[2]} x {source.shape[1]} pixels and {args.goal} "
                         f"{goal.shape[2]} x {goal.shape[1]}: the goal must have the input's size")
    problem = tune.Problem(args.input.name, working(source), working(goal))
    if args.checkpoint is not None:
        try:
            trace, tuner = tune.policy_tune(load_policy(args.checkpoint), problem), "policy"
        except ValueError as e:
            raise PhotoError(f"{args.checkpoint}: {e}") from None
    else:
        tuner = args.optimizer or "cmaes"
        trace = OPTIMIZERS[tuner](problem, args.queries or DEFAULT_QUERIES, args.seed)
    # The result after each query: a policy's last query, an optimiser's best so far.
    results = np.arange(len(trace.psnr_db)) if tuner == "policy" else \
        np.array([trace.best(n) for n in range(1, len(trace.psnr_db) + 1)])
    queries, result_ssim = [], {}
    for i, result in enumerate(results):
        if result not in result_ssim:
            result_ssim[result] = tune.ssim(tune.finished(problem, trace.actions[result]), problem.goal)
        queries.append({"psnr_db": float(trace.psnr_db[i]), "result_psnr_db": float(trace.psnr_db[result]),
                        "result_ssim": result_ssim[result]})
    actions = trace.actions[results[-1]]
    params = params_from_actions(actions)
    out = photos.to_uint8(finish(source[None], params)[0])
    write_png(args.out, out)
    written = out.astype(np.float32) / 255.0
    return {"tuner": tuner, "queries": queries, "params": dict(zip(NAMES, map(float, params))),
            "actions": [float(a) for a in actions], "out": str(args.out),
            "psnr_db": float(psnr_db(written[None], goal[None])[0]), "ssim": tune.ssim(written, goal),
            "input_psnr_db": float(psnr_db(source[None], goal[None])[0])}


def write_png(path: Path, image: np.ndarray) -> None:
    import imageio.v3 as iio

    if not path.parent.is_dir():
        raise PhotoError(f"{path.parent}: no such folder for --out")
    iio.imwrite(path, image.transpose(1, 2, 0), extension=".png")


def print_tune(args: argparse.Namespace, result: dict) -> None:
    for i, q in enumerate(result["queries"], 1):
        print(f"query {i:4d}: {q['psnr_db']:6.2f} dB   "
              f"result {q['result_psnr_db']:6.2f} dB, SSIM {q['result_ssim']:.4f}")
    print("parameters: " + ", ".join(f"{name} {value:.4f}" for name, value in result["params"].items()))
    print(f"{args.out}: PSNR {result['psnr_db']:.2f} dB, SSIM {result['ssim']:.4f} to {args.goal} at full resolution "
          f"(the input: {result['input_psnr_db']:.2f} dB), {result['tuner']}, {len(result['queries'])} queries")


def run_compare(args: argparse.Namespace) -> dict:
    try:
        budgets = tuple(sorted({int(b) for b in args.budgets.split(",")}))
    except ValueError:
        raise PhotoError(f"--budgets takes query counts such as 10,50,200, got {args.budgets!r}") from None
    if args.photos < 1 or budgets[0] < 1:
        raise PhotoError("--photos and every budget must be at least 1")
    policy = None if args.checkpoint is None else load_policy(args.checkpoint)
    started = time.monotonic()
    try:
        problems = tune.held_out_problems(args.photos, args.seed, args.folder, goals=args.goals)
        result = tune.compare(problems, budgets, policy, args.seed)
    except (FileNotFoundError, ValueError) as e:
        raise PhotoError(str(e)) from None
    return result | {"goals": args.goals, "problems": [p.name for p in problems],
                     "seconds": round(time.monotonic() - started, 1)}


def run_enhance(args: argparse.Namespace) -> dict:
    if args.photos < 1:
        raise PhotoError("--photos must be at least 1")
    policy = None if args.checkpoint is None else load_policy(args.checkpoint)
    started = time.monotonic()
    try:
        problems = tune.held_out_problems(args.photos, args.seed, args.folder, PhotoEnhanceEnv)
        result = enhance.compare(problems, policy)
    except (FileNotFoundError, ValueError) as e:
        raise PhotoError(str(e)) from None
    return result | {"problems": [p.name for p in problems], "seconds": round(time.monotonic() - started, 1)}


def print_enhance(result: dict) -> None:
    print(f"{result['photos']} degraded held-out crops ({', '.join(result['problems'])}), {result['seconds']:.0f} s")
    print(f"{'method':<22} {'PSNR (dB)':>10} {'SSIM':>7}")
    labels = {"input": "degraded input", "auto_levels": "auto levels 2-98%", "equalized": "histogram equalised",
              "policy": f"policy, {result['policy_queries']} queries"}
    for name, label in labels.items():
        if result[f"{name}_psnr_db"] is not None:
            print(f"{label:<22} {result[f'{name}_psnr_db']:>10.2f} {result[f'{name}_ssim']:>7.4f}")


def print_compare(result: dict) -> None:
    goals = "another scene's look" if result["goals"] == "looks" else "hidden random parameters"
    print(f"{result['photos']} held-out problems, goals made with {goals} ({', '.join(result['problems'])}), "
          f"{result['seconds']:.0f} s")
    print(f"{'method':<14} {'queries':>7} {'PSNR (dB)':>10} {'SSIM':>7}")
    rows = [("input", 0, result["input_psnr_db"], result["input_ssim"])]
    for method, label in (("random", "random search"), ("cmaes", "CMA-ES")):
        rows += [(label, int(b), psnr, result[f"{method}_ssim"][b]) for b, psnr in result[f"{method}_psnr_db"].items()]
    if result["policy_psnr_db"] is not None:
        rows.append(("policy", result["policy_queries"], result["policy_psnr_db"], result["policy_ssim"]))
    for label, queries, psnr, ssim in rows:
        print(f"{label:<14} {queries:>7} {psnr:>10.2f} {ssim:>7.4f}")


def run_pretrain(args: argparse.Namespace) -> dict:
    import torch

    try:
        config = pretrain.PretrainConfig(env_id=args.env_id, rounds=args.rounds, episodes=args.episodes,
                                         updates=args.updates, lr_schedule=args.lr_schedule, workers=args.workers,
                                         eval_episodes=args.eval_episodes,
                                         source_variety=args.source_variety, residual=args.residual,
                                         seed=args.seed)
    except ValueError as e:
        raise PhotoError(str(e)) from None
    if not args.out.parent.is_dir():
        raise PhotoError(f"{args.out.parent}: no such directory for --out")
    torch.set_num_threads(1)
    policy, evaluation = pretrain.pretrain(config, progress=lambda line: print(line, file=sys.stderr, flush=True))
    try:
        pretrain.save(args.out, policy, config, evaluation)
    except OSError as e:
        raise PhotoError(f"{args.out}: cannot write the checkpoint ({e.strerror})") from None
    return {"checkpoint": str(args.out), "env_id": args.env_id, "source_variety": config.source_variety,
            "psnr_db": evaluation["mean_psnr"],
            "residual_from": policy.spec.get("residual"),
            **{k: evaluation[k] for k in ("episodes", "observations", "losses", "seconds")}}


def print_pretrain(result: dict) -> None:
    print(f"wrote {result['checkpoint']}: its 10 queries reach {result['psnr_db']:.2f} dB on {result['episodes']} "
          f"training episodes ({result['seconds']:.0f} s). Held-out photos: l2r photo compare --checkpoint "
          f"{result['checkpoint']}; on with TD3: l2r up --env-id {result['env_id']} --algo td3 --init-from "
          f"{result['checkpoint']}" + ("" if result["residual_from"] is None else
                                       f" --learner-arg=--residual-from={result['residual_from']}"))


def cli(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        result = {"tune": run_tune, "compare": run_compare, "enhance": run_enhance,
                  "pretrain": run_pretrain}[args.command](args)
    except PhotoError as e:
        print(f"l2r photo {args.command}: {e}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(result))
    elif args.command == "tune":
        print_tune(args, result)
    else:
        {"compare": print_compare, "enhance": print_enhance, "pretrain": print_pretrain}[args.command](result)
    return 0


if __name__ == "__main__":
    sys.exit(cli())
