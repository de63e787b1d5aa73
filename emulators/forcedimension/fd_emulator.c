/* The Force Dimension emulator: the functions of libdrd (SDK 3.16) that a haptic backend
 * uses, over a simulated 3-axis device and a simulated hand. Every other function the
 * forcedimension-core binding binds is a stub in fd_stubs.c (generated).
 *
 * The device: a point mass (FDEMU_MASS kg, default 0.2) with viscous damping (FDEMU_DAMPING
 * N s/m, default 2) inside a spherical workspace (FDEMU_WORKSPACE m radius, default 0.075)
 * whose boundary is a stiff spring (3000 N/m); the applied force is the command (after
 * dhdEnableForce(1)), saturated to the device's limit (FDEMU_MAX_FORCE N, default 12, or
 * dhdSetMaxForce's), plus a simulated hand: a spring (FDEMU_HAND_K N/m, default 50) and
 * damper (5 N s/m) to a target that moves on a circle of FDEMU_HAND_RADIUS m (default 0.01)
 * in the device's x-y plane at FDEMU_HAND_HZ (default 0.25). Positions are quantised to
 * FDEMU_RESOLUTION m (default 1e-5, an encoder's step). Integration: semi-implicit Euler in
 * steps of at most 0.1 ms.
 *
 * Time: FDEMU_CLOCK=wall (default) advances the device by the monotonic time elapsed at each
 * dhdGetPosition; FDEMU_CLOCK=step only when fdemuStep(dt) is called (deterministic).
 *
 * Faults (for tests): FDEMU_UNPLUG_AFTER=N: from the N-th dhdSetForce on, every call to an
 * open device fails (-1, DHD_ERROR_COM) and the device applies no force; FDEMU_FAIL=<function>:<N>: that function fails
 * from its N-th call on (DHD_ERROR); FDEMU_NAN_AFTER=N: from the N-th dhdSetForce on, the
 * position reads NaN; FDEMU_VELOCITY_TIMEOUT=N: the first N calls of dhdGetLinearVelocity after
 * a device opens fail with DHD_ERROR_TIMEOUT (too few positions in the SDK's velocity window
 * yet, as right after opening). FDEMU_DEVICES (default 1, 0: none found), FDEMU_SERIAL (first serial,
 * default 11029), FDEMU_MODEL (system name, default omega.3), FDEMU_UNINITIALIZED=1 (the
 * device needs drdAutoInit), FDEMU_BUTTONS (the button mask). Emulator-only functions:
 * fdemuReset, fdemuStep, fdemuSetClock, fdemuSetButtons, fdemuAppliedForce, fdemuForceEnabled,
 * fdemuSetForceCalls, fdemuIsOpen, fdemuGravity, fdemuEffectorMass, fdemuMaxForce. */
#define _GNU_SOURCE
#include "fd_emulator.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define MAX_DEVICES 4
#define STEP 1e-4
#define WALL_K 3000.0
#define HAND_B 5.0

enum { E_NONE = 0, E_ERROR = 1, E_COM = 2, E_NO_DEVICE = 5, E_NOT_AVAILABLE = 6,
       E_NOT_IMPLEMENTED = 10, E_DEVICE_NOT_READY = 12, E_INVALID_INDEX = 15,
       E_TIMEOUT = 7, E_NOT_ENABLED = 19 };

typedef struct {
    int serial;
    bool open, force_on, initialized, drd_open, gravity;
    double p[3], v[3], cmd[3], applied[3];
    double max_force, effector_mass, t, last_wall;
    unsigned int buttons;
    long set_force_calls, velocity_calls;
} Device;

static Device devs[MAX_DEVICES];
static int n_devices = -1, current = -1, last_error = E_NONE;
static char error_text[256] = "no error";
static char model[64];
static double mass, damping, workspace, max_force_hw, hand_k, hand_radius, hand_hz, resolution;
static bool step_clock = false;
static long unplug_after = -1, nan_after = -1, fail_after = -1, fail_calls = 0;
static long velocity_timeouts = 0;
static char fail_name[64] = "";

static double env_num(const char *name, double dflt) {
    const char *s = getenv(name);
    return (s && *s) ? strtod(s, NULL) : dflt;
}

static double now_s(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

static void set_error(int code, const char *text) {
    last_error = code;
    snprintf(error_text, sizeof error_text, "%s", text);
}

static void setup(void) {
    if (n_devices >= 0) return;
    n_devices = (int)env_num("FDEMU_DEVICES", 1);
    if (n_devices > MAX_DEVICES) n_devices = MAX_DEVICES;
    if (n_devices < 0) n_devices = 0;
    const char *m = getenv("FDEMU_MODEL");
    snprintf(model, sizeof model, "%s", (m && *m) ? m : "omega.3");
    mass = env_num("FDEMU_MASS", 0.2);
    damping = env_num("FDEMU_DAMPING", 2.0);
    workspace = env_num("FDEMU_WORKSPACE", 0.075);
    max_force_hw = env_num("FDEMU_MAX_FORCE", 12.0);
    hand_k = env_num("FDEMU_HAND_K", 50.0);
    hand_radius = env_num("FDEMU_HAND_RADIUS", 0.01);
    hand_hz = env_num("FDEMU_HAND_HZ", 0.25);
    resolution = env_num("FDEMU_RESOLUTION", 1e-5);
    const char *c = getenv("FDEMU_CLOCK");
    step_clock = c && strcmp(c, "step") == 0;
    unplug_after = (long)env_num("FDEMU_UNPLUG_AFTER", -1);
    nan_after = (long)env_num("FDEMU_NAN_AFTER", -1);
    velocity_timeouts = (long)env_num("FDEMU_VELOCITY_TIMEOUT", 0);
    const char *f = getenv("FDEMU_FAIL");
    fail_after = -1;
    fail_calls = 0;
    fail_name[0] = 0;
    if (f && *f) {
        const char *colon = strchr(f, ':');
        size_t len = colon ? (size_t)(colon - f) : strlen(f);
        if (len >= sizeof fail_name) len = sizeof fail_name - 1;
        memcpy(fail_name, f, len);
        fail_name[len] = 0;
        fail_after = colon ? strtol(colon + 1, NULL, 10) : 1;
    }
    int serial = (int)env_num("FDEMU_SERIAL", 11029);
    bool uninit = env_num("FDEMU_UNINITIALIZED", 0) != 0;
    unsigned int buttons = (unsigned int)env_num("FDEMU_BUTTONS", 0);
    for (int i = 0; i < MAX_DEVICES; i++) {
        memset(&devs[i], 0, sizeof devs[i]);
        devs[i].serial = serial + i;
        devs[i].initialized = !uninit;
        devs[i].max_force = max_force_hw;
        devs[i].buttons = buttons;
        devs[i].p[0] = hand_radius;     /* on the hand's circle at t = 0 */
    }
}

/* The device ``id`` (-1: the current one), open; NULL with the error set otherwise. Fails
 * (DHD_ERROR_COM) once unplugged, and the function ``fn`` once FDEMU_FAIL says so. */
static Device *dev(char id, const char *fn) {
    setup();
    int i = id < 0 ? current : (int)id;
    if (i < 0 || i >= n_devices || !devs[i].open) {
        set_error(E_INVALID_INDEX, "invalid device index");
        return NULL;
    }
    Device *d = &devs[i];
    if (unplug_after >= 0 && d->set_force_calls >= unplug_after) {
        d->force_on = false;                /* the device's own safety stops the motors */
        memset(d->applied, 0, sizeof d->applied);
        set_error(E_COM, "communication error between the host and the device");
        return NULL;
    }
    if (fail_after >= 0 && strcmp(fn, fail_name) == 0 && ++fail_calls >= fail_after) {
        set_error(E_ERROR, "undocumented error");
        return NULL;
    }
    return d;
}

static double sat(double f, double lim) { return f > lim ? lim : (f < -lim ? -lim : f); }

static void advance(Device *d, double dt) {
    while (dt > 1e-12) {
        double h = dt < STEP ? dt : STEP;
        dt -= h;
        double w = 2.0 * M_PI * hand_hz * d->t;
        double target[3] = {hand_radius * cos(w), hand_radius * sin(w), 0.0};
        double r = sqrt(d->p[0] * d->p[0] + d->p[1] * d->p[1] + d->p[2] * d->p[2]);
        for (int k = 0; k < 3; k++) {
            double f = d->applied[k] - damping * d->v[k]
                       + hand_k * (target[k] - d->p[k]) - HAND_B * d->v[k];
            if (r > workspace) f -= WALL_K * (r - workspace) * d->p[k] / r;
            d->v[k] += h * f / mass;
        }
        for (int k = 0; k < 3; k++) d->p[k] += h * d->v[k];
        d->t += h;
    }
}

static void wall_advance(Device *d) {
    if (step_clock) return;
    double t = now_s();
    if (d->last_wall > 0.0) {
        double dt = t - d->last_wall;
        advance(d, dt > 0.05 ? 0.05 : dt);     /* a stalled caller: at most 50 ms at once */
    }
    d->last_wall = t;
}

static double quant(double x) { return resolution > 0.0 ? resolution * round(x / resolution) : x; }

void fdemu_not_emulated(const char *name) {
    char text[128];
    snprintf(text, sizeof text, "%s is not emulated", name);
    set_error(E_NOT_IMPLEMENTED, text);
}

/* -- library and devices ---------------------------------------------------------------- */
FDEMU_API void dhdGetSDKVersion(int *major, int *minor, int *release, int *revision) {
    *major = 3; *minor = 16; *release = 0; *revision = 0;
}
FDEMU_API int dhdErrorGetLast(void) { return last_error; }
FDEMU_API char *dhdErrorGetLastStr(void) { return error_text; }
FDEMU_API char *dhdErrorGetStr(int error) { (void)error; return error_text; }
FDEMU_API int dhdGetDeviceCount(void) { setup(); return n_devices; }
FDEMU_API int dhdGetDeviceID(void) { return current; }
FDEMU_API int dhdSetDevice(char id) {
    setup();
    if (id < 0 || id >= n_devices || !devs[(int)id].open) {
        set_error(E_INVALID_INDEX, "invalid device index");
        return -1;
    }
    current = id;
    return 0;
}

static int open_index(int i) {
    setup();
    if (i < 0 || i >= n_devices) {
        set_error(E_NO_DEVICE, "no device found");
        return -1;
    }
    Device *d = &devs[i];
    d->open = true;
    d->force_on = false;
    d->velocity_calls = 0;
    memset(d->cmd, 0, sizeof d->cmd);
    memset(d->applied, 0, sizeof d->applied);
    d->last_wall = 0.0;
    current = i;
    set_error(E_NONE, "no error");
    return i;
}
FDEMU_API int dhdOpen(void) {
    setup();
    for (int i = 0; i < n_devices; i++)
        if (!devs[i].open) return open_index(i);
    set_error(E_NO_DEVICE, "no device found");
    return -1;
}
FDEMU_API int dhdOpenID(char index) { return open_index(index); }
FDEMU_API int dhdOpenSerial(int serial) {
    setup();
    for (int i = 0; i < n_devices; i++)
        if (devs[i].serial == serial) return open_index(i);
    set_error(E_NO_DEVICE, "no device found");
    return -1;
}
FDEMU_API int dhdClose(char id) {
    Device *d = dev(id, "dhdClose");
    if (!d) return -1;
    d->open = d->force_on = d->drd_open = false;
    memset(d->applied, 0, sizeof d->applied);
    return 0;
}
FDEMU_API int dhdStop(char id) {
    Device *d = dev(id, "dhdStop");
    if (!d) return -1;
    d->force_on = false;
    memset(d->applied, 0, sizeof d->applied);
    return 0;
}
FDEMU_API char *dhdGetSystemName(char id) {
    return dev(id, "dhdGetSystemName") ? model : NULL;
}
FDEMU_API int dhdGetSystemType(char id) { return dev(id, "dhdGetSystemType") ? 33 : -1; }
FDEMU_API int dhdGetSerialNumber(unsigned short *sn, char id) {
    Device *d = dev(id, "dhdGetSerialNumber");
    if (!d) return -1;
    *sn = (unsigned short)d->serial;
    return 0;
}
FDEMU_API bool dhdIsLeftHanded(char id) { (void)id; return false; }
FDEMU_API double dhdGetTime(void) { return now_s(); }
FDEMU_API void dhdSleep(double sec) {
    struct timespec ts = {(time_t)sec, (long)((sec - (double)(time_t)sec) * 1e9)};
    nanosleep(&ts, NULL);
}

/* -- force ------------------------------------------------------------------------------ */
FDEMU_API int dhdEnableForce(bool on, char id) {
    Device *d = dev(id, "dhdEnableForce");
    if (!d) return -1;
    d->force_on = on;
    if (!on) memset(d->applied, 0, sizeof d->applied);
    return 0;
}
FDEMU_API int dhdSetForce(double fx, double fy, double fz, char id) {
    Device *d = dev(id, "dhdSetForce");
    if (!d) return -1;
    d->set_force_calls++;
    d->cmd[0] = fx; d->cmd[1] = fy; d->cmd[2] = fz;
    if (!d->force_on) {
        memset(d->applied, 0, sizeof d->applied);
        return 0;
    }
    int rc = 0;
    for (int k = 0; k < 3; k++) {
        double f = d->cmd[k];
        if (!isfinite(f)) f = 0.0;
        d->applied[k] = sat(f, d->max_force);
        if (d->applied[k] != f) rc = 2;         /* DHD_MOTOR_SATURATED */
    }
    return rc;
}
FDEMU_API int dhdGetForce(double *fx, double *fy, double *fz, char id) {
    Device *d = dev(id, "dhdGetForce");
    if (!d) return -1;
    *fx = d->applied[0]; *fy = d->applied[1]; *fz = d->applied[2];
    return 0;
}
FDEMU_API int dhdSetMaxForce(double limit, char id) {
    Device *d = dev(id, "dhdSetMaxForce");
    if (!d) return -1;
    d->max_force = (limit < 0.0 || limit > max_force_hw) ? max_force_hw : limit;
    return 0;
}
FDEMU_API double dhdGetMaxForce(char id) {
    Device *d = dev(id, "dhdGetMaxForce");
    return d ? d->max_force : -1.0;
}
FDEMU_API int dhdSetGravityCompensation(bool on, char id) {
    Device *d = dev(id, "dhdSetGravityCompensation");
    if (!d) return -1;
    d->gravity = on;
    return 0;
}
FDEMU_API int dhdSetEffectorMass(double m, char id) {
    Device *d = dev(id, "dhdSetEffectorMass");
    if (!d) return -1;
    d->effector_mass = m;
    return 0;
}
FDEMU_API int dhdSetBrakes(bool on, char id) {
    (void)on;
    return dev(id, "dhdSetBrakes") ? 0 : -1;
}

/* -- state ------------------------------------------------------------------------------ */
FDEMU_API int dhdGetPosition(double *px, double *py, double *pz, char id) {
    Device *d = dev(id, "dhdGetPosition");
    if (!d) return -1;
    wall_advance(d);
    if (nan_after >= 0 && d->set_force_calls >= nan_after) {
        *px = *py = *pz = NAN;
        return 0;
    }
    *px = quant(d->p[0]); *py = quant(d->p[1]); *pz = quant(d->p[2]);
    return 0;
}
FDEMU_API int dhdGetLinearVelocity(double *vx, double *vy, double *vz, char id) {
    Device *d = dev(id, "dhdGetLinearVelocity");
    if (!d) return -1;
    if (d->velocity_calls++ < velocity_timeouts) {
        set_error(E_TIMEOUT, "timeout: too few positions for the velocity estimate");
        return -1;
    }
    *vx = d->v[0]; *vy = d->v[1]; *vz = d->v[2];
    return 0;
}
FDEMU_API unsigned int dhdGetButtonMask(char id) {
    Device *d = dev(id, "dhdGetButtonMask");
    return d ? d->buttons : 0u;
}
FDEMU_API int dhdGetButton(int index, char id) {
    Device *d = dev(id, "dhdGetButton");
    if (!d) return -1;
    return (index >= 0 && index < 32) ? (int)(d->buttons >> index & 1u) : 0;
}

/* -- drd: calibration ------------------------------------------------------------------- */
FDEMU_API int drdOpen(void) {
    int i = dhdOpen();
    if (i >= 0) devs[i].drd_open = true;
    return i;
}
FDEMU_API int drdOpenID(char id) {
    setup();
    if (id < 0 || id >= n_devices) {
        set_error(E_NO_DEVICE, "no device found");
        return -1;
    }
    if (!devs[(int)id].open) open_index(id);
    devs[(int)id].drd_open = true;
    return id;
}
FDEMU_API int drdClose(char id) { return dhdClose(id); }
FDEMU_API bool drdIsSupported(char id) { return dev(id, "drdIsSupported") != NULL; }
FDEMU_API bool drdIsInitialized(char id) {
    Device *d = dev(id, "drdIsInitialized");
    return d && d->initialized;
}
FDEMU_API int drdAutoInit(char id) {
    Device *d = dev(id, "drdAutoInit");
    if (!d) return -1;
    if (!d->drd_open) {
        set_error(E_NOT_AVAILABLE, "feature not available: drdOpenID first");
        return -1;
    }
    d->initialized = true;
    return 0;
}
FDEMU_API int drdStop(bool force_on, char id) {
    Device *d = dev(id, "drdStop");
    if (!d) return -1;
    d->force_on = force_on;
    return 0;
}

/* -- emulator only ---------------------------------------------------------------------- */
/* Forget every device and read the environment again (FDEMU_*): a test's fresh emulator. */
FDEMU_API void fdemuReset(void) {
    n_devices = -1;
    current = -1;
    set_error(E_NONE, "no error");
    setup();
}
/* Advance the current device by dt s (FDEMU_CLOCK=step; with the wall clock as well). */
FDEMU_API int fdemuStep(double dt) {
    setup();
    if (current < 0) return -1;
    advance(&devs[current], dt);
    return 0;
}
/* Choose the clock: 1 stepped (fdemuStep only), 0 the wall clock (FDEMU_CLOCK's choice). */
FDEMU_API void fdemuSetClock(int stepped) {
    setup();
    step_clock = stepped != 0;
}
FDEMU_API void fdemuSetButtons(unsigned int mask) {
    setup();
    for (int i = 0; i < MAX_DEVICES; i++) devs[i].buttons = mask;
}
/* What the device applies now (N): zero while force is disabled or the device closed. */
FDEMU_API void fdemuAppliedForce(int index, double *f) {
    setup();
    Device *d = &devs[index < 0 ? (current < 0 ? 0 : current) : index];
    for (int k = 0; k < 3; k++) f[k] = (d->open && d->force_on) ? d->applied[k] : 0.0;
}
FDEMU_API int fdemuForceEnabled(int index) { setup(); return devs[index].open && devs[index].force_on; }
FDEMU_API long fdemuSetForceCalls(int index) { setup(); return devs[index].set_force_calls; }
FDEMU_API int fdemuIsOpen(int index) { setup(); return devs[index].open; }
FDEMU_API int fdemuGravity(int index) { setup(); return devs[index].gravity; }
FDEMU_API double fdemuEffectorMass(int index) { setup(); return devs[index].effector_mass; }
FDEMU_API double fdemuMaxForce(int index) { setup(); return devs[index].max_force; }
