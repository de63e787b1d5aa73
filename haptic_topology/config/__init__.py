"""Configuration: parameter specs and params-file checks (:mod:`.params`), the per-node
settings classes with each setting's one range (:mod:`.settings`), their resolution with a
scenario into the core's frozen configuration objects (:mod:`.resolve`) and the node parameter
tables (:mod:`.node_params`). No rclpy: the nodes declare what these modules describe."""
