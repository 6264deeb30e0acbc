"""The edge daemon: a KISS-ICP mapper per robot, acks, map queryable, liveliness."""
