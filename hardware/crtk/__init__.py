"""A CRTK / ROS 2 arm (the da Vinci Research Kit's) as the slave, over DDS without ROS: the message layouts
(messages), the loopback-only participants (dds), the console's end (slave), a fake arm for tests and benchmarks
(fake_arm, a process of its own) and the rig builder (rig)."""
