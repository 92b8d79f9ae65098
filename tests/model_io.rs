//! Integration tests: model_io.
