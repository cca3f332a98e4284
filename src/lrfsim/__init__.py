"""lrfsim: a MuJoCo testbench for rotating 2D laser range finders (servo-turned Hokuyo UTM-30LX-EW)."""

__version__ = "0.1.0"
