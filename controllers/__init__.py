"""The flight stack's control: the feedback-linearised LQR outer loop (`controllers.lqr`) and the
attitude autopilot and mixer (`controllers.autopilot`). Import the modules directly."""
