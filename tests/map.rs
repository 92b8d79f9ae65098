//! Integration tests: map.
