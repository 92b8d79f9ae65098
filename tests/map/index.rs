//! Integration tests: the map's spatial index (filled on the `mapproj` branch).
