"""What the service is told: its settings (environment), the robot config (YAML) and the
timing budget derived from both."""
