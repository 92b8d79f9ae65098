//! Integration tests: map io.
