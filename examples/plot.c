/* examples/plot.c -- placeholder: the SVG plot writer of make figures. */
#include "plot.h"
