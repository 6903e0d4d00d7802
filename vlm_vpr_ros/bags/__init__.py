"""rosbag2 bags: make (MCAP or sqlite3, written by rosbags), read (MCAP folders/files, sqlite3),
replay onto live topics and evaluate offline. An edge package: it may import rclpy, message
packages and mcap; the localization core never imports it."""

from vlm_vpr_ros.bags.reader import BagReader, RawMessage, TopicInfo, deserialize, open_bag

__all__ = ["BagReader", "RawMessage", "TopicInfo", "deserialize", "open_bag"]
