//! Estimating the texel camera's sensor model from captures of a calibration target.
