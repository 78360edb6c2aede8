"""Conversions between gscan_ros domain values and serialized ROS 2 messages (CDR bytes).

Every conversion of the nodes and of the bag code goes through here: `<value>_to_cdr`
gives the bytes a node publishes and a bag stores, `cdr_to_<value>` reads them back
(MessageFormatError for bytes that do not hold the message). Messages are built with
rosbags' pure-Python type store, so bags are read and written without ROS installed.
"""
from msg_adapters.action import action_to_cdr, cdr_to_action
from msg_adapters.cdr import cdr_to_msg, message_class, message_definition, msg_to_cdr, type_hash
from msg_adapters.command_graph import cdr_to_graph, graph_to_cdr
from msg_adapters.episode_status import cdr_to_episode_status, episode_status_to_cdr
from msg_adapters.errors import MessageFormatError
from msg_adapters.header import grid_header, time_ns
from msg_adapters.image import attention_to_cdr, cdr_to_attention, cdr_to_image, image_header, image_to_cdr
from msg_adapters.observation import ObservationDecoder, cdr_to_observation, observation_to_cdr
from msg_adapters.situation import cdr_to_situation, situation_to_cdr
from msg_adapters.text import cdr_to_string_bytes, cdr_to_text, text_to_cdr
from msg_adapters.world_reset import cdr_to_reset, reset_to_cdr

__all__ = [
    "MessageFormatError",
    "ObservationDecoder",
    "action_to_cdr",
    "attention_to_cdr",
    "cdr_to_action",
    "cdr_to_attention",
    "cdr_to_episode_status",
    "cdr_to_graph",
    "cdr_to_image",
    "cdr_to_msg",
    "cdr_to_observation",
    "cdr_to_reset",
    "cdr_to_situation",
    "cdr_to_string_bytes",
    "cdr_to_text",
    "episode_status_to_cdr",
    "graph_to_cdr",
    "grid_header",
    "image_header",
    "image_to_cdr",
    "message_class",
    "message_definition",
    "msg_to_cdr",
    "observation_to_cdr",
    "reset_to_cdr",
    "situation_to_cdr",
    "text_to_cdr",
    "time_ns",
    "type_hash",
]
