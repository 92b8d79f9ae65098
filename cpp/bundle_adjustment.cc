// Ceres bundle adjustment: filled in by the solver work.
#include <ceres/ceres.h>
