"""ROS 2 over Zenoh without a ROS install: what an ``rmw_zenoh`` node puts on the wire, rebuilt with
zenoh-python and the ``rosbags`` package (CDR serde and RIHS01 type hashes, offline).

* ``keys``: topic key expressions ``<domain>/<topic>/<pkg>::msg::dds_::<Type>_/<RIHS01 hash>`` and
  the graph's liveliness tokens ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<kind>/...`` with their QoS
  strings (rmw_zenoh_cpp ``src/detail/liveliness_utils.cpp``);
* ``attachment``: the sequence number, source timestamp and GID sent with every sample
  (``attachment_helpers.cpp``);
* ``typestore``: CDR (de)serialisation and type hashes, with vision_msgs registered;
* ``messages``: the messages zoffload publishes (odometry, tf, maps, detections);
* ``pointcloud`` and ``image``: sensor_msgs/PointCloud2 and Image/CompressedImage to numpy by
  their own field descriptions;
* ``session`` and ``node``: the Zenoh session on the ROS side and a node's declarations.

Everything but ``session`` and ``node`` is pure and tested without Zenoh. Checked against the
rmw_zenoh_cpp sources of Jazzy 0.2.10 / Kilted 0.6.7 (see README "On a ROS 2 robot").
"""
