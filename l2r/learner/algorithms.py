"""Which of the learner's algorithms learn on-policy.

An on-policy algorithm takes its batches from the replay server's queue table (each transition
once, none older than the queue's lag bound, with the acting policy's log-probabilities), runs
eagerly, and publishes weights after every batch; the others sample the replay table. A3C is
on-policy without batches: its actors send gradients of their own rollouts instead. Every
place that depends on the difference (the learner's tables and checks, `l2r up`'s plan) asks
this set.
"""

ON_POLICY = frozenset({"ppo", "a2c", "a3c", "reinforce", "trpo", "acktr"})
"""The --algo names of the on-policy algorithms."""
