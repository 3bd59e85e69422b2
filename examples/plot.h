#ifndef BRT_EXAMPLES_PLOT_H
#define BRT_EXAMPLES_PLOT_H
#include "common.h"
#endif
