"""Record: scripted-expert demonstrations into a LeRobotDataset (``so101-sim record``), replay.

Workers (``so101_sim.workers``) run ``worker.EpisodeRecorder`` (env, expert, video encoder)
on one ``episode.run_episode`` each; ``loop`` hands out seeds and writes results in seed
order through ``so101_sim.dataset``. ``demo`` renders a short expert episode to images.
"""

from so101_sim.record.api import record, replay, replay_versions
from so101_sim.record.episode import check_dart_noise, expert_options, run_episode

__all__ = ["check_dart_noise", "expert_options", "record", "replay", "replay_versions",
           "run_episode"]
