"""The episode record: how actors store episodes in MCAP and how viewers read them back.

- ``schema``: topics, schemas and metadata names (the format itself).
- ``encode``: fast encoders for the per-step messages.
- ``body``: the runner's shapes and muscle paths, as JSON, URDF and Foxglove scene.
- ``write``: one episode's file, from its static channels to its summary and final name.
- ``read``: one episode file back into numpy arrays (complete or interrupted files).
- ``recover``: ``python -m l2r.episodes.recover FILE.mcap.part`` repairs an interrupted file.

- ``live``: the low-rate frames actors publish while a viewer watches.

Actors log through ``l2r.actors.episode_log.EpisodeLogger`` (which episodes, off the stepping
thread, under a disk budget); the viewer is ``l2r view`` (``l2r.view``). docs/episodes.md
describes the format and what each tool shows.
"""
