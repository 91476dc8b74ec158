"""The map for ROS 2 robots: an rclpy node (``overgrid ros2``) and a native rmw_zenoh publisher
(``overgrid rmw-zenoh``) that needs no ROS installation.

``grid_message`` turns an ``OccupancyMap`` into the fields of the ROS messages (pure numpy), and
``rmw_zenoh`` spells rmw_zenoh's key expressions, liveliness tokens and attachment (pure strings
and bytes); ``node`` and ``native`` wire them to rclpy or Zenoh.
"""
