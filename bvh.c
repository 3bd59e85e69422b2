/* bvh.c -- placeholder */
#include "batchrt.h"
