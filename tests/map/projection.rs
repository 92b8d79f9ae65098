//! Integration tests: map projection into cameras (filled on the `mapproj` branch).
