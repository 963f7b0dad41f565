"""Live sensor streams into the suite, without rclpy: the mapping file (which driver topic and field
is which contract channel), the batching of per-sample driver messages into contract SensorBlocks,
and the per-sample streams the DAQ simulator publishes. The ROS side is nodes/daq_adapter.py and
nodes/daq_sim.py (docs/daq_stream.md)."""
