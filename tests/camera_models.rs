//! Integration tests: camera_models.
