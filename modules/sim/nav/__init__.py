"""The simulated navigation sensors (IMU, DGPS, speedometer, two compasses): their error models,
the process that publishes them from the truth, and the offline replay and accuracy tools the
navigation filter is tested and measured with."""
