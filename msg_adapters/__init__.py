"""Pure conversions between gscan_ros domain objects and ROS 2 messages (std_msgs, sensor_msgs).

Every conversion of the nodes and of the bag code goes through here.
"""
from msg_adapters.action import action_to_msg, cdr_to_action, msg_to_action
from msg_adapters.cdr import cdr_to_msg, cdr_to_string_bytes, msg_to_cdr
from msg_adapters.command_graph import graph_to_msg, msg_to_graph
from msg_adapters.episode_status import cdr_to_episode_status, episode_status_to_msg, msg_to_episode_status
from msg_adapters.errors import MessageFormatError
from msg_adapters.header import grid_header, time_msg, time_ns
from msg_adapters.image import attention_to_msg, image_to_msg, msg_to_attention, msg_to_image
from msg_adapters.observation import ObservationDecoder, cdr_to_observation, msg_to_observation, observation_to_msg
from msg_adapters.situation import msg_to_situation, situation_to_msg
from msg_adapters.text import cdr_to_text, msg_to_text, text_to_msg
from msg_adapters.world_reset import msg_to_reset, reset_to_msg

__all__ = [
    "MessageFormatError",
    "ObservationDecoder",
    "action_to_msg",
    "attention_to_msg",
    "cdr_to_action",
    "cdr_to_episode_status",
    "cdr_to_msg",
    "cdr_to_observation",
    "cdr_to_string_bytes",
    "cdr_to_text",
    "episode_status_to_msg",
    "graph_to_msg",
    "grid_header",
    "image_to_msg",
    "msg_to_action",
    "msg_to_attention",
    "msg_to_cdr",
    "msg_to_episode_status",
    "msg_to_graph",
    "msg_to_image",
    "msg_to_observation",
    "msg_to_reset",
    "msg_to_situation",
    "msg_to_text",
    "observation_to_msg",
    "reset_to_msg",
    "situation_to_msg",
    "text_to_msg",
    "time_msg",
    "time_ns",
]
