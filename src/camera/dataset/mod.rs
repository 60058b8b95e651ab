//! Dataset folder readers (TUM, EuRoC, TartanAir, plain folder).
