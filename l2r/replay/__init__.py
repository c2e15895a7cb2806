"""The replay server (`l2r-replay`): experience storage and sampling for learners, over Zenoh."""
