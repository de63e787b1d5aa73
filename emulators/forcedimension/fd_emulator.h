/* The Force Dimension emulator: a libdrd that forcedimension-core loads in place of the
 * vendor's (see README.md beside this file). */
#ifndef FD_EMULATOR_H
#define FD_EMULATOR_H
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#define FDEMU_API __attribute__((visibility("default")))

/* Record that an unemulated function was called: it fails with DHD_ERROR_NOT_IMPLEMENTED. */
void fdemu_not_emulated(const char *name);

#endif
