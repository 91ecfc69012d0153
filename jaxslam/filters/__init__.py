"""Generic filters (they never name a paper): EKF core, EKF-SLAM engine."""
