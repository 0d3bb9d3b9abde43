"""rosbag2 recordings (sqlite3 or MCAP, through rosbags): message types, reading, atomic writing, message builders."""
