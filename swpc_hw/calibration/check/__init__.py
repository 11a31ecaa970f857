"""The check: the file in force against new data, its verdict, the shape compared
without motion capture, the trends over a robot's history."""
