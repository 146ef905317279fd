"""Robot and engineer side of the fleet depot: the robot helper, the spool agent and the REST client."""
