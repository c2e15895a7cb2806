"""Training recipes of `l2r up`: every hyperparameter of a job, per task family and algorithm.

A recipe is a flat table of values, one per setting, keyed by (family, algorithm). The family
comes from the task (l2r.families): `runner` for the Learning to Run runner (`l2r/Run-v0`,
`l2r/RunOpenSim-v0`), `pixels` for the camera tasks (`l2r/dmc-...`), `photo` for the
photo-finishing tasks (`l2r/PhotoTune-v0`, `l2r/PhotoEnhance-v0`), `standard` for any other gymnasium task (Hopper-v5,
Walker2d-v5). `l2r up --recipe` picks another family's recipe, and each setting has an `l2r up`
flag of its own name that replaces the recipe's value.

The settings span the three daemons: the replay server's (`REPLAY_FLAGS`), the actors'
(`ACTOR_SETTINGS`) and the learner's (every other one, an `l2r-learner` flag of the same name).
Left out, and the same in every recipe of an algorithm: PPO and REINFORCE standardise their
advantages per minibatch and A2C does not; `--learner-arg` sets that.

The learner's own defaults (`SACConfig`, `TD3Config`, `PPOConfig`, `A2CConfig`, `A3CConfig`, `ReinforceConfig`)
stay the 2017 reference solution's, CleanRL's, Stable-Baselines3's and Spinning Up's; `l2r up`
passes every value of the recipe, so the learner's command line shows it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

from l2r.encoders import IMAGE_VIEWS
from l2r.families import PHOTO, PIXELS, RUNNER, STANDARD, family_of
from l2r.learner.ppo import LAG_CORRECTIONS, OPTIMIZERS
from l2r.learner.td3 import ACTOR_LOSSES
from l2r.policy import ACTIVATIONS
from l2r.sim import randomize_refusal

Value = bool | int | float | str

# The body drawn anew each episode on the runner's MuJoCo envs (the actors' --randomize): what the
# A/Bs of docs/training.md ran.
RUNNER_RANDOMIZATION = ("strength=0.05,tendon_slack=0.02,fiber_length=0.02,mass=0.05,contact_stiffness=0.2,"
                        "contact_damping=0.2,friction=0.2,delay=0.5")

# The course the runner's SAC trains on (the actors' --difficulty-schedule): flat ground for each
# actor's first million env steps, about the time its gait takes to form on 2 cores, then the
# obstacles and weak psoas of the 2017 final round; the evaluators keep --difficulty.
RUNNER_CURRICULUM = "0:0,1000000:2"

RECIPES: dict[tuple[str, str], dict[str, Value]] = {
    # Tuned on the runner on a 2-core CPU (docs/training.md, "The recipe"): rewards of 0.01-0.03 m
    # a step scaled up, a cool start, the body's symmetry and running statistics doing the rest.
    # No warm-up: every runner figure was measured with actors acting with the learner's untrained
    # policy from its first publication on (until 2026-11-26 that first policy ended any warm-up).
    # Since 2026-11-27 each episode's body is drawn anew and the entropy target is half SAC's: the
    # two together learnt on each of three seeds and kept 14.0-15.1 m in OpenSim; randomisation
    # alone kept 6.4 and 15.8 m on two of them (docs/training.md, "Levers for robustness").
    # Since 2026-11-27 (later) its actors move to the obstacle course after a million env steps: on
    # two seeds the kept policies ran 5.3 and 6.5 m over the obstacles in OpenSim (the recipe
    # without it: -0.8 and 2.5), 12.8 and 14.0 m on flat ground (15.1 and 14.7), and OpenSim kept
    # with the port for longer (docs/training.md, "The obstacle course from a million steps on").
    (RUNNER, "sac"): dict(
        hidden="256,256", activation="elu", layer_norm=True, batch_size=256, lr=3e-4, gamma=0.99, tau=0.005,
        reward_scale=10.0, initial_alpha=0.1, target_entropy_per_action=-0.5, update_repeat=1, n_step=1,
        publish_every=50,
        relative_x=True, normalize_obs=True, mirror=True,
        min_replay=10_000, samples_per_insert=0.0, hold_actors=False,
        random_steps=0, envs_per_actor=4, action_repeat=3, frame_stack=1, randomize=RUNNER_RANDOMIZATION,
        difficulty_schedule=RUNNER_CURRICULUM,
    ),
    # Stable-Baselines3's and CleanRL's SAC for MuJoCo tasks: raw observations, learning from 5,000
    # steps on, one gradient step per env step (samples-per-insert = batch-size / update-repeat,
    # held both ways), the actor acting with each new policy.
    (STANDARD, "sac"): dict(
        hidden="256,256", activation="relu", layer_norm=False, batch_size=256, lr=3e-4, gamma=0.99, tau=0.005,
        reward_scale=1.0, initial_alpha=1.0, target_entropy_per_action=-1.0, update_repeat=1, n_step=1,
        publish_every=1,
        relative_x=False, normalize_obs=False, mirror=False,
        min_replay=5_000, samples_per_insert=256.0, hold_actors=True,
        random_steps=5_000, envs_per_actor=1, action_repeat=1, frame_stack=1,
    ),
    # CleanRL's PPO (PPOConfig), but for the lag correction, with the runner's observation options.
    (RUNNER, "ppo"): dict(
        hidden="64,64", activation="tanh", layer_norm=False, batch_size=2048, epochs=10, minibatches=32, lr=3e-4,
        gamma=0.99, gae_lambda=0.95, clip=0.2, value_coef=0.5, entropy_coef=0.0, max_grad_norm=0.5,
        lag_correction="ratio", optimizer="adam", reward_scale=1.0,
        relative_x=True, normalize_obs=True,
        random_steps=0, envs_per_actor=4, action_repeat=3,
    ),
    # The same for other tasks: observations standardised (as CleanRL's wrapper does), one step per action.
    (STANDARD, "ppo"): dict(
        hidden="64,64", activation="tanh", layer_norm=False, batch_size=2048, epochs=10, minibatches=32, lr=3e-4,
        gamma=0.99, gae_lambda=0.95, clip=0.2, value_coef=0.5, entropy_coef=0.0, max_grad_norm=0.5,
        lag_correction="ratio", optimizer="adam", reward_scale=1.0,
        relative_x=False, normalize_obs=True,
        random_steps=0, envs_per_actor=4, action_repeat=1,
    ),
    # A2C as Stable-Baselines3 and RL Baselines3 Zoo train it on MuJoCo tasks (A2CConfig: RMSprop at
    # 7e-4, n-step returns, the value loss at twice PPO's weight, observations standardised), but
    # for the batch: 32 transitions, not SB3's 5 (n_steps 5 of one env). The queue holds two batches
    # and must take an actor's 64-transition chunk whole; 32 is the smallest batch it can. One env
    # per actor: each env sends its own chunks, and four envs' chunks would wait through versions
    # enough to go stale (--queue-max-lag) before the learner's small batches reached them. On the
    # runner with its observation options and action repeat; not measured on the runner yet.
    (RUNNER, "a2c"): dict(
        hidden="64,64", activation="tanh", layer_norm=False, batch_size=32, epochs=1, minibatches=1, lr=7e-4,
        gamma=0.99, gae_lambda=1.0, clip=0.2, value_coef=1.0, entropy_coef=0.0, max_grad_norm=0.5,
        lag_correction="ratio", optimizer="rmsprop", reward_scale=1.0,
        relative_x=True, normalize_obs=True,
        random_steps=0, envs_per_actor=1, action_repeat=3,
    ),
    # The same for other tasks: one step per action.
    (STANDARD, "a2c"): dict(
        hidden="64,64", activation="tanh", layer_norm=False, batch_size=32, epochs=1, minibatches=1, lr=7e-4,
        gamma=0.99, gae_lambda=1.0, clip=0.2, value_coef=1.0, entropy_coef=0.0, max_grad_norm=0.5,
        lag_correction="ratio", optimizer="rmsprop", reward_scale=1.0,
        relative_x=False, normalize_obs=True,
        random_steps=0, envs_per_actor=1, action_repeat=1,
    ),
    # REINFORCE with a value baseline at Spinning Up VPG's values (ReinforceConfig): 4,000 transitions
    # and one Adam step at 3e-4 per update, Monte-Carlo returns (lambda 1). On the runner with its
    # observation options and action repeat; not measured on the runner yet.
    (RUNNER, "reinforce"): dict(
        hidden="64,64", activation="tanh", layer_norm=False, batch_size=4000, epochs=1, minibatches=1, lr=3e-4,
        gamma=0.99, gae_lambda=1.0, clip=0.2, value_coef=0.5, entropy_coef=0.0, max_grad_norm=0.5,
        lag_correction="ratio", optimizer="adam", reward_scale=1.0,
        relative_x=True, normalize_obs=True,
        random_steps=0, envs_per_actor=4, action_repeat=3,
    ),
    # The same for other tasks: raw observations as Spinning Up's, one step per action.
    (STANDARD, "reinforce"): dict(
        hidden="64,64", activation="tanh", layer_norm=False, batch_size=4000, epochs=1, minibatches=1, lr=3e-4,
        gamma=0.99, gae_lambda=1.0, clip=0.2, value_coef=0.5, entropy_coef=0.0, max_grad_norm=0.5,
        lag_correction="ratio", optimizer="adam", reward_scale=1.0,
        relative_x=False, normalize_obs=False,
        random_steps=0, envs_per_actor=4, action_repeat=1,
    ),
    # sb3-contrib's TRPO at RL Baselines3 Zoo's MuJoCo values (TRPOConfig: 2048 transitions an update,
    # KL bound 0.01, 25 conjugate-gradient steps damped 0.1, the value network 20 passes of Adam at
    # 1e-3 in minibatches of 128), PPO's networks, observation options and actors, but for the lag.
    (RUNNER, "trpo"): dict(
        hidden="64,64", activation="tanh", layer_norm=False, batch_size=2048, lr=1e-3, gamma=0.99, gae_lambda=0.95,
        max_kl=0.01, cg_steps=25, cg_damping=0.1, line_search_shrink=0.8, line_search_steps=10, value_epochs=20,
        value_minibatch_size=128, lag_correction="ratio", reward_scale=1.0,
        relative_x=True, normalize_obs=True,
        random_steps=0, envs_per_actor=4, action_repeat=3,
    ),
    (STANDARD, "trpo"): dict(
        hidden="64,64", activation="tanh", layer_norm=False, batch_size=2048, lr=1e-3, gamma=0.99, gae_lambda=0.95,
        max_kl=0.01, cg_steps=25, cg_damping=0.1, line_search_shrink=0.8, line_search_steps=10, value_epochs=20,
        value_minibatch_size=128, lag_correction="ratio", reward_scale=1.0,
        relative_x=False, normalize_obs=True,
        random_steps=0, envs_per_actor=4, action_repeat=1,
    ),
    # The ACKTR paper's K-FAC (a trust region of 0.001, damping 0.01, statistics decay 0.99) and its
    # MuJoCo script's rollout of 2500 transitions with lambda 0.97; PPO's networks, observation
    # options and actors, but for the lag. The step size is the paper's Atari one, 0.25, fixed
    # (target_kl 0), with momentum 0: with momentum 0.9 the steps added up to a KL near 1 between
    # consecutive policies against the bound of 0.001 (Hopper-v5: 43 after 1M env steps; with
    # momentum 0, 375). The paper's MuJoCo step size, adapted to a KL of 0.002 (ACKTRConfig's
    # default, momentum 0.9), reached 172 at 200k: not yet run to 1M (docs/training.md, "TRPO and ACKTR").
    (RUNNER, "acktr"): dict(
        hidden="64,64", activation="tanh", layer_norm=False, batch_size=2500, lr=0.25, gamma=0.99, gae_lambda=0.97,
        max_kl=0.001, momentum=0.0, target_kl=0.0, kfac_damping=0.01, kfac_decay=0.99, value_coef=1.0,
        value_fisher_coef=1.0, entropy_coef=0.0, lag_correction="ratio", reward_scale=1.0,
        relative_x=True, normalize_obs=True,
        random_steps=0, envs_per_actor=4, action_repeat=3,
    ),
    (STANDARD, "acktr"): dict(
        hidden="64,64", activation="tanh", layer_norm=False, batch_size=2500, lr=0.25, gamma=0.99, gae_lambda=0.97,
        max_kl=0.001, momentum=0.0, target_kl=0.0, kfac_damping=0.01, kfac_decay=0.99, value_coef=1.0,
        value_fisher_coef=1.0, entropy_coef=0.0, lag_correction="ratio", reward_scale=1.0,
        relative_x=False, normalize_obs=True,
        random_steps=0, envs_per_actor=4, action_repeat=1,
    ),
    # The runner's SAC recipe with TD3's own values (its paper's, as CleanRL and SB3 keep them): a
    # constant exploration std of 0.1, target smoothing 0.2 clipped at 0.5, the actor every 2nd step.
    # Not measured on the runner yet.
    (RUNNER, "td3"): dict(
        hidden="256,256", activation="elu", layer_norm=True, batch_size=256, lr=3e-4, gamma=0.99, tau=0.005,
        reward_scale=10.0, update_repeat=1, publish_every=50,
        n_step=1, policy_delay=2, target_noise=0.2, scheduled_target_noise=False, noise_clip=0.5,
        online_target_actor=False, actor_loss="q1",
        exploration_std_start=0.1, exploration_std_end=0.1, exploration_std_updates=250_000,
        relative_x=True, normalize_obs=True, mirror=True,
        min_replay=10_000, samples_per_insert=0.0, hold_actors=False,
        random_steps=0, envs_per_actor=4, action_repeat=3, frame_stack=1,
    ),
    # CleanRL's TD3 for MuJoCo tasks: standard/sac's networks and one gradient step per env step,
    # learning from 25,000 uniform random steps on.
    (STANDARD, "td3"): dict(
        hidden="256,256", activation="relu", layer_norm=False, batch_size=256, lr=3e-4, gamma=0.99, tau=0.005,
        reward_scale=1.0, update_repeat=1, publish_every=1,
        n_step=1, policy_delay=2, target_noise=0.2, scheduled_target_noise=False, noise_clip=0.5,
        online_target_actor=False, actor_loss="q1",
        exploration_std_start=0.1, exploration_std_end=0.1, exploration_std_updates=250_000,
        relative_x=False, normalize_obs=False, mirror=False,
        min_replay=25_000, samples_per_insert=256.0, hold_actors=True,
        random_steps=25_000, envs_per_actor=1, action_repeat=1, frame_stack=1,
    ),
    # DrQ-v2's, for the camera tasks (TD3 on 3 stacked 84 x 84 frames; the learner's image defaults
    # add the frame stack of 3 and random shifts of 4 pixels): 1024-wide networks, n-step 3, the
    # exploration std from 1.0 to 0.1 over its "easy" tasks' 100,000 env steps (50,000 updates at
    # one per 2 env steps; its medium tasks take 250,000), the target's noise that same std clipped
    # at 0.3, the actor every update, learning after 2,000 uniform random steps; the target action
    # from the online actor, and the actor ascending the lower critic at its action plus that noise
    # (TD3's target actor and Q1 left cartpole-swingup at 74 for an hour, seed 0; these reached 194
    # at 20k frames: docs/training.md). Weights go out every 10th update rather than each: an image
    # policy is 8 MB, mostly its encoder's projection.
    (PIXELS, "td3"): dict(
        hidden="1024,1024", activation="relu", layer_norm=False, batch_size=256, lr=1e-4, gamma=0.99, tau=0.01,
        reward_scale=1.0, update_repeat=1, publish_every=10,
        n_step=3, policy_delay=1, target_noise=0.2, scheduled_target_noise=True, noise_clip=0.3,
        online_target_actor=True, actor_loss="min-noisy",
        exploration_std_start=1.0, exploration_std_end=0.1, exploration_std_updates=50_000,
        relative_x=False, normalize_obs=False, mirror=False,
        min_replay=2_000, samples_per_insert=128.0, hold_actors=True,
        # action_repeat 1: the camera task itself holds each action for DrQ-v2's 2 suite steps.
        random_steps=2_000, envs_per_actor=1, action_repeat=1, encoder="drq",
    ),
    # DrQ's (Kostrikov, Yarats and Fergus, 2021; its repository's config.yaml), SAC on the camera tasks:
    # 1024-wide networks, learning rate 1e-3, tau 0.01, a cool start (temperature 0.1) towards SAC's
    # entropy target, batches of 512 (the paper's), one update per env step, learning after 1,000
    # uniform random steps; the learner's image defaults add its frame stack of 3 and shifts of 4
    # pixels. l2r's: the actor and the targets every update (DrQ's every 2nd), the encoder's conv
    # layers shared as DrQ-v2 shares them (no target encoder).
    (PIXELS, "sac"): dict(
        hidden="1024,1024", activation="relu", layer_norm=False, batch_size=512, lr=1e-3, gamma=0.99, tau=0.01,
        reward_scale=1.0, initial_alpha=0.1, target_entropy_per_action=-1.0, update_repeat=1, n_step=1,
        publish_every=10,
        relative_x=False, normalize_obs=False, mirror=False,
        min_replay=1_000, samples_per_insert=512.0, hold_actors=True,
        random_steps=1_000, envs_per_actor=1, action_repeat=1, encoder="drq",
    ),
    # The pixels recipe made RLPixTuner's where its training script (bash/train.sh, envs/run_sb3.py)
    # says: the discount 0.9, tau 0.007 (its EMA rate 0.993), the exploration std 0.02, the
    # target's noise 0.04 clipped at 0.01 (a quarter of it), the actor every 2nd update and
    # [400, 300] networks (Stable-Baselines3's TD3 defaults, which it keeps), learning after 100
    # random steps. Its 10-step episodes, 64 x 64 images and reward (the PSNR change x 0.01) are
    # the env's own. l2r's: one learning rate where it has 5e-4 for the actor and 5e-5 for the
    # critics (DrQ-v2's 1e-4, between), batches of 128 (its script's default is 2), one gradient
    # step per env step. Both images are aligned with each other, so no random shift (a shift per
    # field would misalign them), and no frame stack: the state holds the parameters so far.
    (PHOTO, "td3"): dict(
        hidden="400,300", activation="relu", layer_norm=False, batch_size=128, lr=1e-4, gamma=0.9, tau=0.007,
        reward_scale=1.0, update_repeat=1, publish_every=10,
        n_step=1, policy_delay=2, target_noise=0.04, scheduled_target_noise=False, noise_clip=0.01,
        online_target_actor=False, actor_loss="q1",
        exploration_std_start=0.02, exploration_std_end=0.02, exploration_std_updates=250_000,
        relative_x=False, normalize_obs=False, mirror=False,
        min_replay=100, samples_per_insert=128.0, hold_actors=True,
        random_steps=100, envs_per_actor=1, action_repeat=1, frame_stack=1, augment_pad=0, encoder="drq",
    ),
}
# PPO for the photo tasks through their statistics (l2r/PhotoEnhanceStats-v0, l2r/PhotoTuneStats-v0):
# standard/ppo (CleanRL's continuous-action PPO) at a quarter of its rollout, 512 transitions (51
# episodes of 10 steps), its minibatches of 64 and 10 epochs kept, so that the ~40 env steps/s of a
# loaded 2-core machine make an update every 10-15 s rather than every minute; photo/td3's
# discount (RLPixTuner's 0.9) over the 10-step episodes.
RECIPES[PHOTO, "ppo"] = {**RECIPES[STANDARD, "ppo"], "batch_size": 512, "minibatches": 8, "gamma": 0.9}
# A3C: A2C's recipe with its rollout, the 5 steps of one environment per gradient (Stable-Baselines3's
# n_steps; A3C's t_max), that each actor turns into a gradient at the weights it acted with. A
# gradient more than 4 versions behind the learner's is refused.
RECIPES |= {(family, "a3c"): {**RECIPES[family, "a2c"], "batch_size": 5, "max_gradient_staleness": 4}
            for family in (RUNNER, STANDARD)}
# The runner's other recipes keep the body fixed and the ground flat (both measured with SAC
# alone), and say so.
for (family, algo), table in RECIPES.items():
    if family == RUNNER:
        table.setdefault("randomize", "")
        table.setdefault("difficulty_schedule", "")

# What each setting is, for its `l2r up` flag's help.
SETTINGS: dict[str, str] = {
    "hidden": "hidden layer widths of every network, comma-separated",
    "activation": "hidden activation",
    "layer_norm": "LayerNorm after each hidden layer",
    "batch_size": "transitions per batch; for the on-policy algorithms, per update (their rollout)",
    "lr": "learning rate of every network (and of SAC's temperature)",
    "gamma": "discount per action",
    "tau": "Polyak rate of the target networks (SAC, TD3)",
    "reward_scale": "multiplier on rewards",
    "initial_alpha": "the entropy temperature at the start, learnt from there (SAC)",
    "update_repeat": "gradient steps per sampled batch (SAC, TD3)",
    "publish_every": "updates between weight publications; 1: actors act with the newest weights (SAC, TD3; the "
                     "on-policy algorithms publish after every batch)",
    "n_step": "steps summed into each sampled reward before the bootstrap (SAC, TD3)",
    "policy_delay": "the actor steps and the targets follow on every Nth update (TD3)",
    "target_noise": "std of the noise on the target action (TD3's target policy smoothing)",
    "scheduled_target_noise": "the target action's noise takes the current exploration std instead of "
                              "--target-noise (TD3)",
    "noise_clip": "the target action's noise is clipped to +- this (TD3)",
    "online_target_actor": "the target action is the online actor's (DrQ-v2), not its Polyak copy's (TD3)",
    "actor_loss": "what the actor ascends: q1, the first critic at its own action; min-noisy, the lower critic at "
                  "its action plus the exploration noise clipped at --noise-clip, as DrQ-v2 (TD3)",
    "exploration_std_start": "std of the actors' Gaussian exploration noise at update 0 (TD3)",
    "exploration_std_end": "... and after --exploration-std-updates updates (TD3)",
    "exploration_std_updates": "learner updates over which the exploration std goes linearly from start to end "
                               "(TD3)",
    "epochs": "passes over each batch (PPO, A2C, REINFORCE)",
    "minibatches": "minibatches per pass, one gradient step each (PPO, A2C, REINFORCE)",
    "gae_lambda": "lambda of GAE; 1: returns to the end of each trajectory piece (the on-policy algorithms)",
    "clip": "clip range of the probability ratio, 1 +- clip (PPO, A2C, REINFORCE)",
    "value_coef": "weight of the value loss, half the squared error (PPO, A2C, REINFORCE, ACKTR)",
    "entropy_coef": "weight of the entropy bonus (PPO, A2C, REINFORCE, ACKTR)",
    "max_grad_norm": "gradient norm clip (PPO, A2C, REINFORCE)",
    "max_gradient_staleness": "a gradient computed at weights more than this many versions behind the learner's is "
                              "refused (A3C)",
    "lag_correction": "what the on-policy algorithms do about the actors' policy lag (docs/learner.md)",
    "optimizer": "adam or rmsprop (PPO, A2C, REINFORCE)",
    "max_kl": "the trust region: how far, in mean KL from the policy before it, one step may move the policy "
              "(TRPO; ACKTR: its quadratic approximation)",
    "cg_steps": "conjugate-gradient steps for the natural gradient (TRPO)",
    "cg_damping": "multiple of the identity added to the Fisher (TRPO)",
    "line_search_shrink": "each backtracking try takes this fraction of the step before (TRPO)",
    "line_search_steps": "backtracking tries before the policy step is given up (TRPO)",
    "value_epochs": "passes of the value network's Adam over each batch (TRPO)",
    "value_minibatch_size": "transitions per value-network step (TRPO)",
    "momentum": "SGD momentum on the scaled natural gradient (ACKTR)",
    "target_kl": "the KL each step should make: the step size adapts to it, as the ACKTR paper's MuJoCo code; 0: "
                 "--lr fixed (ACKTR)",
    "kfac_damping": "added to the Kronecker-factored Fisher before it is inverted (ACKTR)",
    "kfac_decay": "running-average decay of the K-FAC factors (ACKTR)",
    "value_fisher_coef": "weight of the value network's sampled log-likelihood in the Fisher statistics (ACKTR)",
    "relative_x": "networks see world x coordinates as distances from the pelvis (the runner alone)",
    "normalize_obs": "networks see observations standardised by running statistics",
    "mirror": "the learner swaps the legs of a random half of each batch (symmetry augmentation; SAC, TD3, the "
              "runner alone)",
    "min_replay": "transitions stored before the learner starts (SAC, TD3; of several --replay-shards, each waits "
                  "for its share)",
    "samples_per_insert": "replay rate limit: sampled transitions per inserted one (0: no limit; SAC, TD3)",
    "hold_actors": "with --samples-per-insert, the replay server holds the actors back while they are ahead of the "
                   "learner, so the ratio holds both ways (SAC, TD3)",
    "random_steps": "uniform random steps of each actor before it uses the policy (warm-up)",
    "randomize": "a new body each episode on the l2r/Run-v0 and l2r/RunWarp-v0 actors (not the --opensim-actors): "
                 "each named factor uniform in 1 +- FRACTION (at most 0.5): strength, tendon_slack, fiber_length "
                 "(per muscle), mass (per segment), contact_stiffness, contact_damping, friction (the ground); "
                 "delay=P: the probability that an episode's excitations act one physics step late; '' (an empty "
                 "value): none (l2r-actor --help says more; the runner alone)",
    "difficulty_schedule": "the runner's course of rising difficulty, stages entered in order, e.g. "
                           "0:0,300000:1,600000:2 (at the actor's own env steps) or 0:0,6m:2 (once its last 20 "
                           "training episodes average 6 m); the evaluators keep --difficulty (or --eval-difficulty); "
                           "'' (an empty value): --difficulty throughout, as a --difficulty other than 0 also asks",
    "target_entropy_per_action": "SAC's entropy target per action dimension, towards which the temperature is "
                                 "learnt (-1: SAC's -act-dim; a --learner-arg=--target-entropy wins) (SAC)",
    "envs_per_actor": "environments per actor, batched in one policy call",
    "action_repeat": "0.01 s environment steps per action on the runner, environment steps per action on another "
                     "task (stored in checkpoints for `l2r eval`)",
    "frame_stack": "observations stacked into each input, oldest first: a camera task's frames, or the vector's "
                   "history (SAC, TD3; unset: the learner's 3 for images)",
    "augment_pad": "image observations: pixels of DrQ's random shift (SAC, TD3; 0: none; unset: the learner's 4)",
    "encoder": "image observations: the encoder of each image field, drq (DrQ-v2's convolutions) or dual "
               "(RLPixTuner's global and local paths, images of 32 x 32 or more; l2r-learner --help) (SAC, TD3)",
}
# Settings whose values are one of a few names.
CHOICES: dict[str, tuple[str, ...]] = {"activation": tuple(ACTIVATIONS), "lag_correction": LAG_CORRECTIONS,
                                       "optimizer": OPTIMIZERS, "encoder": tuple(IMAGE_VIEWS),
                                       "actor_loss": ACTOR_LOSSES}

# Settings added to the recipes after runs were made, each with the value those runs trained with:
# a run whose launch.json recorded a recipe without one resumes with that value (l2r up --resume).
ADDED_SINCE: dict[str, Value] = {"randomize": "", "target_entropy_per_action": -1.0, "difficulty_schedule": ""}

# The replay server's settings, under their l2r-replay flags.
REPLAY_FLAGS = {"min_replay": "--min-size", "samples_per_insert": "--samples-per-insert",
                "hold_actors": "--hold-actors"}
# The actors' settings (l2r up hands each to the processes that need it).
ACTOR_SETTINGS = ("random_steps", "envs_per_actor", "action_repeat", "randomize", "difficulty_schedule")
# Settings that read the runner's body (its x coordinates, its legs): off on any other task.
RUNNER_BODY = ("relative_x", "mirror")


@dataclass(frozen=True)
class Recipe:
    """The values a job trains with: its recipe's, each replaced by its flag where one was given."""

    name: str
    """family/algorithm, e.g. runner/sac."""
    values: dict[str, Value]
    origins: dict[str, str]
    """Where each value came from: 'recipe' or 'flag'; for the runner's options on another task, why they are off."""
    unused: tuple[str, ...]
    """Settings given as flags that this algorithm has no use for (--mirror with PPO)."""

    def describe(self) -> str:
        """One line: each value, grouped by where it came from (the unused flags aside)."""
        groups: dict[str, list[str]] = {}
        for name, value in self.values.items():
            origin = {"recipe": "from the recipe", "flag": "from flags"}.get(self.origins[name], self.origins[name])
            groups.setdefault(origin, []).append(f"{name} {_shown(value)}")
        return f"recipe {self.name}: " + "; ".join(f"{origin}: {', '.join(items)}" for origin, items in groups.items())

    def to_dict(self) -> dict:
        return {"name": self.name, "values": {name: {"value": value, "from": self.origins[name]}
                                              for name, value in self.values.items()}, "unused": list(self.unused)}


def resolve(env_id: str, algo: str, family: str | None, flags: Mapping[str, Value | None]) -> Recipe:
    """The recipe of `family` (None: the family of `env_id`) for `algo`, each value replaced by its
    flag in `flags` unless that is None."""
    family = family or family_of(env_id)
    table = RECIPES[family, algo]
    values, origins = {}, {}
    for name, value in table.items():
        given = flags.get(name)
        values[name], origins[name] = (value, "recipe") if given is None else (given, "flag")
        if name in RUNNER_BODY and values[name] and family_of(env_id) != RUNNER:
            values[name], origins[name] = False, f"off on {env_id}, the runner's alone"
        if name == "randomize" and values[name] and origins[name] == "recipe" and randomize_refusal(env_id):
            values[name], origins[name] = "", f"off on {env_id}, the MuJoCo runner's alone"
        if name == "difficulty_schedule" and values[name] and origins[name] == "recipe" and family_of(env_id) != RUNNER:
            values[name], origins[name] = "", f"off on {env_id}, the runner's alone"
    unused = tuple(name for name, value in flags.items() if value is not None and name not in table)
    return Recipe(f"{family}/{algo}", values, origins, unused)


def _shown(value: Value) -> str:
    if isinstance(value, bool) or value == "":
        return "on" if value else "off"
    return f"{value:,}" if isinstance(value, int) else f"{value:g}" if isinstance(value, float) else value


def shown_values(name: str) -> str:
    """A setting's value in each recipe that has it, e.g. 'runner/sac 10, standard/sac 1'."""
    return ", ".join(f"{family}/{algo} {_shown(table[name])}" for (family, algo), table in RECIPES.items()
                     if name in table)
