"""What l2r daemons share: key expressions with their QoS, messages, session set-up, replay client."""

from l2r.protocol.keys import (
    ACK_QOS, EPISODE_QOS, EXPERIENCE_QOS, FRAMES_QOS, GRADIENT_QOS, PRIORITY_QOS, ROUND_QOS, SAMPLE_QOS,
    STATS_QOS, VERSION_QOS, WEIGHTS_QOS, Keys, QoS, check_name, parse_alive, shard_of,
)
from l2r.protocol.messages import (
    MAX_MESSAGE_BYTES, PROTOCOL_VERSION, ActorId, ActorIdRequest, EpisodeSummary, EvaluationRound, ExperienceChunk,
    Frame, Gradient, LearnerVersion, Message, NotReady, PriorityUpdate, ProtocolError, ReplayAck, SampleBatch,
    SampleRequest, Stats, Weights, decode, encode, encode_gathered,
)
from l2r.protocol.frames_codec import FrameCompressor
from l2r.protocol.observations import FieldSpec, ObservationSpec, as_fields
from l2r.protocol.replay_client import ReplayClient
from l2r.protocol.session import (
    LISTENER_GRACE, DaemonSettings, Rejections, await_listener, configure_logging, reuse_large_buffers, session_config,
    wait_alive, watched, with_reply_pool,
)

__all__ = [
    "ACK_QOS", "EPISODE_QOS", "EXPERIENCE_QOS", "FRAMES_QOS", "GRADIENT_QOS", "PRIORITY_QOS", "ROUND_QOS", "SAMPLE_QOS",
    "STATS_QOS", "VERSION_QOS", "WEIGHTS_QOS", "Keys", "QoS", "check_name", "parse_alive", "shard_of",
    "MAX_MESSAGE_BYTES", "PROTOCOL_VERSION", "ActorId", "ActorIdRequest", "EpisodeSummary", "EvaluationRound",
    "ExperienceChunk", "Frame", "Gradient", "LearnerVersion", "Message", "NotReady", "PriorityUpdate", "ProtocolError",
    "ReplayAck", "SampleBatch", "SampleRequest", "Stats", "Weights", "decode", "encode", "encode_gathered",
    "FrameCompressor", "FieldSpec", "ObservationSpec", "as_fields", "ReplayClient",
    "LISTENER_GRACE", "DaemonSettings", "Rejections", "await_listener", "configure_logging", "reuse_large_buffers",
    "session_config", "wait_alive", "watched", "with_reply_pool",
]
