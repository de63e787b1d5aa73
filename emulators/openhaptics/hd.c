/*
 * An emulator of OpenHaptics' HD API (libHD.so) with a simulated 3D Systems Touch behind it,
 * for testing haptic_topology's `openhaptics` backend through the unmodified pyOpenHaptics
 * package without a device. Built by scripts/setup.sh:
 *
 *     gcc -O2 -fPIC -shared -pthread -Wl,-soname,libHD.so -o <venv>/lib/haptic_topology/libHD.so
 *         emulators/openhaptics/hd.c -lm
 *
 * The functions below have the signatures and types of OpenHaptics' hd.h, hdDefines.h and
 * hdScheduler.h (HDErrorInfo returned by value; HHD, HDenum, HDerror unsigned int; HDboolean
 * unsigned char; HDulong unsigned long). Semantics as documented for the HDAPI:
 *
 *  - hdInitDevice(name) opens the device of that configuration name and makes it current; it
 *    returns HD_INVALID_HANDLE and records an error when it cannot (an unknown name:
 *    HD_COMM_CONFIG_ERROR; a device open already: HD_DEVICE_ALREADY_INITIATED). Without
 *    HD_EMU_DEVICES there is one device, whatever the name; with it, the devices it lists
 *    (HD_DEFAULT_DEVICE, a null name, is the first). hdMakeCurrentDevice selects the device that
 *    hdGetString, hdGetDoublev, ... answer for. hdDisableDevice closes one; closing the last one
 *    stops the scheduler. The devices share one simulated mechanism (drive one at a time).
 *  - hdStartScheduler starts the servo thread: every 1/rate s (hdSetSchedulerRate, default
 *    1000 Hz; absolute deadlines on CLOCK_MONOTONIC) it advances the simulated device by one
 *    period with the force committed last, then calls the scheduled callbacks in order of
 *    priority. Woken late, it advances the device by every period passed and calls the
 *    callbacks once (the ticks between are skipped, counted by hdEmuSkippedTicks). A callback returning HD_CALLBACK_CONTINUE is called again next tick, one
 *    returning HD_CALLBACK_DONE is removed. hdScheduleSynchronous blocks the caller until its
 *    callback has returned HD_CALLBACK_DONE; hdScheduleAsynchronous returns at once.
 *  - hdBeginFrame snapshots the device state (what hdGetDoublev / hdGetIntegerv return until
 *    hdEndFrame) and starts the frame's force at zero; hdSetDoublev(HD_CURRENT_FORCE) sets it;
 *    hdEndFrame commits it to the motors (clamped to HD_NOMINAL_MAX_FORCE while
 *    HD_MAX_FORCE_CLAMPING is enabled, zero while HD_FORCE_OUTPUT is disabled). Frames nest;
 *    the outermost commits. Outside a frame the getters read the newest state.
 *  - hdGetError pops the oldest error not yet read (HD_SUCCESS when none).
 *
 * Units and axes are OpenHaptics': mm, mm/s, N; x right, y up, z toward the user. The
 * simulated device: a point mass (HD_EMU_MASS kg) with viscous friction (HD_EMU_DAMPING N s/m),
 * the motor force, and a simulated hand: a spring (HD_EMU_HAND_K N/m) and damper (HD_EMU_HAND_B
 * N s/m) to a target moving on a figure eight of HD_EMU_HAND_MM mm at HD_EMU_HAND_HZ Hz in the
 * x-y plane. Positions are quantised to HD_EMU_RESOLUTION_MM (the encoders); the velocity is a
 * first-order filtered difference of quantised positions, as the HDAPI computes it.
 *
 * Emulator-only settings and fault injection (environment variables, read at hdInitDevice):
 *   HD_EMU_UNPLUG_AT=N   from servo tick N on: the device is gone (zero force, state frozen),
 *                        every hdBeginFrame records HD_COMM_ERROR
 *   HD_EMU_NAN_AT=N      from servo tick N on, for HD_EMU_NAN_FOR ticks (default: ever), the
 *                        position, transform and velocity read NaN
 *   HD_EMU_STALL_AT=N    from servo tick N on the scheduler calls no callback (a hung
 *                        servo loop); hdStopScheduler still stops it
 *   HD_EMU_FAIL=<fn>     that function fails: hdInitDevice returns HD_INVALID_HANDLE with
 *                        HD_COMM_CONFIG_ERROR; hdEnable, hdStartScheduler, hdSetDoublev record
 *                        HD_INVALID_OPERATION and do nothing
 *   HD_EMU_BUTTONS       button mask (HD_CURRENT_BUTTONS), default 0
 *   HD_EMU_BUTTON_TICKS=N1,N2,...  the buttons of HD_EMU_BUTTONS are held from servo tick N1,
 *                        released from N2, held again from N3, ... (none before N1; at most 16)
 *   HD_EMU_INKWELL       1: the stylus is in the inkwell (HD_CURRENT_INKWELL_SWITCH)
 *   HD_EMU_CALIBRATION   ok | needs_update | needs_manual_input (hdCheckCalibration)
 *   HD_EMU_MAX_FORCE     HD_NOMINAL_MAX_FORCE in N (default 3.3, a Touch's)
 *   HD_EMU_MODEL, HD_EMU_SERIAL   the identity strings
 *   HD_EMU_DEVICES="<name>=<serial>,..."  several devices (at most 8), by configuration name,
 *                        each with its serial number (HD_DEVICE_SERIAL_NUMBER)
 * and the exported hdEmuApplied() (the newest committed force and when), hdEmuSetButtons(),
 * hdEmuTicks() and hdEmuTickNs() (when the newest servo tick began) for tests and benches.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

typedef unsigned int HDuint;
typedef unsigned char HDboolean;
typedef unsigned long HDulong;
typedef unsigned short HDushort;
typedef int HDint;
typedef float HDfloat;
typedef double HDdouble;
typedef long HDlong;
typedef unsigned int HDerror;
typedef unsigned int HDenum;
typedef const char *HDstring;
typedef unsigned int HHD;
typedef unsigned int HDCallbackCode;
typedef unsigned long HDSchedulerHandle;
typedef HDCallbackCode (*HDSchedulerCallback)(void *pUserData);

typedef struct {
    HDerror errorCode;
    int internalErrorCode;
    HHD hHD;
} HDErrorInfo;

#define HD_SUCCESS 0x0000
#define HD_INVALID_ENUM 0x0100
#define HD_INVALID_VALUE 0x0101
#define HD_INVALID_OPERATION 0x0102
#define HD_BAD_HANDLE 0x0104
#define HD_EXCEEDED_MAX_FORCE 0x0201
#define HD_FORCE_ERROR 0x0204
#define HD_DEVICE_ALREADY_INITIATED 0x0301
#define HD_COMM_ERROR 0x0302
#define HD_COMM_CONFIG_ERROR 0x0303
#define HD_TIMER_ERROR 0x0304
#define HD_ILLEGAL_BEGIN 0x0400
#define HD_ILLEGAL_END 0x0401
#define HD_SCHEDULER_FULL 0x0501

#define HD_CURRENT_BUTTONS 0x2000
#define HD_CURRENT_SAFETY_SWITCH 0x2001
#define HD_CURRENT_INKWELL_SWITCH 0x2002
#define HD_CURRENT_POSITION 0x2050
#define HD_CURRENT_VELOCITY 0x2051
#define HD_CURRENT_TRANSFORM 0x2052
#define HD_CURRENT_ANGULAR_VELOCITY 0x2053
#define HD_CURRENT_JOINT_ANGLES 0x2100
#define HD_CURRENT_GIMBAL_ANGLES 0x2150
#define HD_VERSION 0x2500
#define HD_DEVICE_MODEL_TYPE 0x2501
#define HD_DEVICE_DRIVER_VERSION 0x2502
#define HD_DEVICE_VENDOR 0x2503
#define HD_DEVICE_SERIAL_NUMBER 0x2504
#define HD_DEVICE_FIRMWARE_VERSION 0x2505
#define HD_INPUT_DOF 0x2553
#define HD_OUTPUT_DOF 0x2554
#define HD_CALIBRATION_STYLE 0x2555
#define HD_UPDATE_RATE 0x2600
#define HD_INSTANTANEOUS_UPDATE_RATE 0x2601
#define HD_NOMINAL_MAX_FORCE 0x2603
#define HD_NOMINAL_MAX_CONTINUOUS_FORCE 0x2604
#define HD_CURRENT_FORCE 0x2700
#define HD_LAST_FORCE 0x2800
#define HD_FORCE_OUTPUT 0x4000
#define HD_MAX_FORCE_CLAMPING 0x4001
#define HD_FORCE_RAMPING 0x4002
#define HD_SOFTWARE_FORCE_LIMIT 0x4003
#define HD_ONE_FRAME_LIMIT 0x4004
#define HD_CALIBRATION_OK 0x5000
#define HD_CALIBRATION_NEEDS_UPDATE 0x5001
#define HD_CALIBRATION_NEEDS_MANUAL_INPUT 0x5002
#define HD_CALIBRATION_INKWELL (1 << 2)
#define HD_CALLBACK_DONE 0
#define HD_CALLBACK_CONTINUE 1
#define HD_INVALID_HANDLE 0xFFFFFFFFu
#define MAX_DEVICES 8

#define MAX_ERRORS 32
#define MAX_CALLBACKS 32

typedef struct {
    double pos[3];      /* mm, quantised */
    double vel[3];      /* mm/s */
    int buttons;
    int inkwell;
} Snapshot;

typedef struct {
    HDSchedulerCallback fn;
    void *data;
    HDushort priority;
    int sync;                   /* 1: a caller waits for it in hdScheduleSynchronous */
    int done;
    unsigned long id;
} Callback;

static pthread_mutex_t lock = PTHREAD_MUTEX_INITIALIZER;
static pthread_cond_t cond = PTHREAD_COND_INITIALIZER;
static pthread_t thread;
static int running, stopping, force_enabled, clamping = 1;
/* The devices: configuration names and serials (HD_EMU_DEVICES), which are open, the current
 * one (a handle is index + 1). n_devices 0: one device, any name, serial HD_EMU_SERIAL. */
static char dev_name[MAX_DEVICES][64], dev_serial[MAX_DEVICES][64];
static int n_devices, dev_open[MAX_DEVICES], n_open;
static HHD current_dev = HD_INVALID_HANDLE;
static unsigned long rate = 1000;
static Callback callbacks[MAX_CALLBACKS];
static int n_callbacks;
static unsigned long next_id = 1;
static HDErrorInfo errors[MAX_ERRORS];
static int n_errors;

/* The simulated device (SI inside: m, m/s, N) and its settings. */
static double x[3], v[3], reported[3], vfilt[3], committed[3];
static long long tick_count, unplug_at = -1, nan_at = -1, nan_for = -1, stall_at = -1;
static double sim_t, mass = 0.1, damping = 1.0, hand_k = 100.0, hand_b = 2.0;
static double hand_mm = 10.0, hand_hz = 0.5, resolution_mm = 0.055, max_force = 3.3;
static int buttons, inkwell, calibration = HD_CALIBRATION_OK;
static int button_mask, n_button_ticks;
static long long button_ticks[16];
static char fail_fn[64], model[64] = "Touch", serial[64] = "EMU-00001";
static long long committed_ns, commits, tick_ns, skipped;

/* The frame (the scheduler thread's, or an application thread's outside the scheduler). */
static __thread int frame_depth;
static __thread Snapshot frame;
static __thread double frame_force[3];

static long long now_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static void push_error(HDerror code, int internal) {
    pthread_mutex_lock(&lock);
    if (n_errors < MAX_ERRORS) {
        errors[n_errors].errorCode = code;
        errors[n_errors].internalErrorCode = internal;
        errors[n_errors].hHD = current_dev;
        n_errors++;
    }
    pthread_mutex_unlock(&lock);
}

static int fails(const char *fn) { return strcmp(fail_fn, fn) == 0; }

static double env_double(const char *name, double fallback) {
    const char *s = getenv(name);
    return s && *s ? strtod(s, NULL) : fallback;
}

static long long env_ll(const char *name, long long fallback) {
    const char *s = getenv(name);
    return s && *s ? strtoll(s, NULL, 10) : fallback;
}

static void env_text(const char *name, char *out, size_t n, const char *fallback) {
    const char *s = getenv(name);
    snprintf(out, n, "%s", s && *s ? s : fallback);
}

static int unplugged(void) { return unplug_at >= 0 && tick_count >= unplug_at; }
static int nan_now(void) {
    return nan_at >= 0 && tick_count >= nan_at && (nan_for < 0 || tick_count < nan_at + nan_for);
}

/* The hand's target (m) at time t: a figure eight in the x-y plane. */
static void hand_target(double t, double out[3]) {
    double w = 2.0 * M_PI * hand_hz * t, a = 1e-3 * hand_mm;
    out[0] = a * sin(w);
    out[1] = 0.5 * a * sin(2.0 * w);
    out[2] = 0.0;
}

/* One servo period of the simulated device (lock held). */
static void step_device(double dt) {
    double target[3];
    if (unplugged()) {          /* no power to the motors; nothing is read any more */
        committed[0] = committed[1] = committed[2] = 0.0;
        tick_count++;
        return;
    }
    hand_target(sim_t, target);
    for (int i = 0; i < 3; i++) {
        double f = committed[i] + hand_k * (target[i] - x[i]) - (hand_b + damping) * v[i];
        v[i] += f / mass * dt;
        x[i] += v[i] * dt;
        double q = 1e-3 * resolution_mm;
        double r = q > 0.0 ? q * round(x[i] / q) : x[i];
        double raw = (r - reported[i]) / dt;
        vfilt[i] += 0.2 * (raw - vfilt[i]);
        reported[i] = r;
    }
    sim_t += dt;
    tick_count++;
    if (n_button_ticks) {       /* HD_EMU_BUTTON_TICKS: held after an odd number of them */
        int passed = 0;
        while (passed < n_button_ticks && tick_count >= button_ticks[passed]) passed++;
        buttons = passed % 2 ? button_mask : 0;
    }
}

static void read_state(Snapshot *s) {
    pthread_mutex_lock(&lock);
    int bad = nan_now();
    for (int i = 0; i < 3; i++) {
        s->pos[i] = bad ? NAN : 1e3 * reported[i];
        s->vel[i] = bad ? NAN : 1e3 * vfilt[i];
    }
    s->buttons = buttons;
    s->inkwell = inkwell;
    pthread_mutex_unlock(&lock);
}

/* ---- device ------------------------------------------------------------------------------ */
static int is_open(HHD h) { return h >= 1 && h <= MAX_DEVICES && dev_open[h - 1]; }

/* HD_EMU_DEVICES="<name>=<serial>,...": the devices by name (none: one device, any name). */
static void read_devices(void) {
    const char *s = getenv("HD_EMU_DEVICES");
    n_devices = 0;
    while (s && *s && n_devices < MAX_DEVICES) {
        const char *end = strchr(s, ',');
        size_t len = end ? (size_t)(end - s) : strlen(s);
        const char *eq = memchr(s, '=', len);
        size_t name_len = eq ? (size_t)(eq - s) : len;
        snprintf(dev_name[n_devices], sizeof dev_name[0], "%.*s", (int)name_len, s);
        snprintf(dev_serial[n_devices], sizeof dev_serial[0], "%.*s",
                 eq ? (int)(len - name_len - 1) : 0, eq ? eq + 1 : "");
        n_devices++;
        s = end ? end + 1 : NULL;
    }
}

/* The settings and the simulated mechanism, anew (at the first hdInitDevice, none open). */
static void reset_device(void) {
    unplug_at = env_ll("HD_EMU_UNPLUG_AT", -1);
    nan_at = env_ll("HD_EMU_NAN_AT", -1);
    nan_for = env_ll("HD_EMU_NAN_FOR", -1);
    stall_at = env_ll("HD_EMU_STALL_AT", -1);
    mass = env_double("HD_EMU_MASS", 0.1);
    damping = env_double("HD_EMU_DAMPING", 1.0);
    hand_k = env_double("HD_EMU_HAND_K", 100.0);
    hand_b = env_double("HD_EMU_HAND_B", 2.0);
    hand_mm = env_double("HD_EMU_HAND_MM", 10.0);
    hand_hz = env_double("HD_EMU_HAND_HZ", 0.5);
    resolution_mm = env_double("HD_EMU_RESOLUTION_MM", 0.055);
    max_force = env_double("HD_EMU_MAX_FORCE", 3.3);
    buttons = (int)env_ll("HD_EMU_BUTTONS", 0);
    button_mask = buttons;
    n_button_ticks = 0;
    for (const char *b = getenv("HD_EMU_BUTTON_TICKS"); b && *b && n_button_ticks < 16;) {
        char *end;
        button_ticks[n_button_ticks++] = strtoll(b, &end, 10);
        b = *end == ',' ? end + 1 : NULL;
    }
    if (n_button_ticks) buttons = 0;
    inkwell = (int)env_ll("HD_EMU_INKWELL", 0);
    env_text("HD_EMU_MODEL", model, sizeof model, "Touch");
    env_text("HD_EMU_SERIAL", serial, sizeof serial, "EMU-00001");
    const char *cal = getenv("HD_EMU_CALIBRATION");
    calibration = !cal || !*cal || !strcmp(cal, "ok") ? HD_CALIBRATION_OK
        : !strcmp(cal, "needs_update") ? HD_CALIBRATION_NEEDS_UPDATE
        : HD_CALIBRATION_NEEDS_MANUAL_INPUT;
    memset(x, 0, sizeof x);
    memset(v, 0, sizeof v);
    memset(reported, 0, sizeof reported);
    memset(vfilt, 0, sizeof vfilt);
    memset(committed, 0, sizeof committed);
    tick_count = 0;
    sim_t = 0.0;
    commits = 0;
    committed_ns = 0;
    skipped = 0;
    n_errors = 0;
    force_enabled = 0;
    clamping = 1;
}

HHD hdInitDevice(HDstring pConfigName) {
    env_text("HD_EMU_FAIL", fail_fn, sizeof fail_fn, "");
    if (fails("hdInitDevice")) {
        push_error(HD_COMM_CONFIG_ERROR, -1);
        return HD_INVALID_HANDLE;
    }
    pthread_mutex_lock(&lock);
    int first = n_open == 0;
    if (first) read_devices();
    int index = 0;
    if (n_devices > 0 && pConfigName && *pConfigName) {
        while (index < n_devices && strcmp(dev_name[index], pConfigName) != 0) index++;
    }
    int known = n_devices == 0 || index < n_devices;
    int already = known && dev_open[index];
    pthread_mutex_unlock(&lock);
    if (!known) {
        push_error(HD_COMM_CONFIG_ERROR, -3);
        return HD_INVALID_HANDLE;
    }
    if (already) {
        push_error(HD_DEVICE_ALREADY_INITIATED, 0);
        return HD_INVALID_HANDLE;
    }
    pthread_mutex_lock(&lock);
    if (first) reset_device();
    dev_open[index] = 1;
    n_open++;
    current_dev = (HHD)(index + 1);
    pthread_mutex_unlock(&lock);
    return current_dev;
}

HHD hdGetCurrentDevice(void) { return current_dev; }

void hdMakeCurrentDevice(HHD hHD) {
    if (!is_open(hHD)) push_error(HD_BAD_HANDLE, 0);
    else current_dev = hHD;
}

void hdStopScheduler(void);

void hdDisableDevice(HHD hHD) {
    if (!is_open(hHD)) {
        push_error(HD_BAD_HANDLE, 0);
        return;
    }
    if (n_open == 1) hdStopScheduler();
    pthread_mutex_lock(&lock);
    dev_open[hHD - 1] = 0;
    n_open--;
    if (current_dev == hHD) {
        current_dev = HD_INVALID_HANDLE;
        for (int i = 0; i < MAX_DEVICES; i++)
            if (dev_open[i]) current_dev = (HHD)(i + 1);
    }
    if (n_open == 0) {
        memset(committed, 0, sizeof committed);
        force_enabled = 0;
    }
    pthread_mutex_unlock(&lock);
}

HDErrorInfo hdGetError(void) {
    HDErrorInfo e = {HD_SUCCESS, 0, current_dev};
    pthread_mutex_lock(&lock);
    if (n_errors > 0) {
        e = errors[0];
        memmove(errors, errors + 1, (size_t)(n_errors - 1) * sizeof errors[0]);
        n_errors--;
    }
    pthread_mutex_unlock(&lock);
    return e;
}

HDstring hdGetErrorString(HDerror code) {
    switch (code) {
    case HD_SUCCESS: return "No error";
    case HD_COMM_ERROR: return "Communication error";
    case HD_COMM_CONFIG_ERROR: return "Communication configuration error";
    case HD_INVALID_OPERATION: return "Invalid operation";
    case HD_INVALID_ENUM: return "Invalid enumeration";
    case HD_BAD_HANDLE: return "Invalid device handle";
    case HD_EXCEEDED_MAX_FORCE: return "Exceeded maximum force";
    case HD_FORCE_ERROR: return "Force error";
    case HD_ILLEGAL_BEGIN: return "Illegal begin frame";
    case HD_ILLEGAL_END: return "Illegal end frame";
    default: return "Error";
    }
}

HDstring hdGetString(HDenum pname) {
    switch (pname) {
    case HD_DEVICE_MODEL_TYPE: return model;
    case HD_DEVICE_VENDOR: return "haptic_topology emulator of OpenHaptics";
    case HD_DEVICE_SERIAL_NUMBER:
        return n_devices > 0 && is_open(current_dev) ? dev_serial[current_dev - 1] : serial;
    case HD_DEVICE_DRIVER_VERSION: return "emulator";
    case HD_DEVICE_FIRMWARE_VERSION: return "emulator";
    case HD_VERSION: return "3.4.0 (emulator)";
    default:
        push_error(HD_INVALID_ENUM, (int)pname);
        return "";
    }
}

static int enable_param(HDenum cap, int on) {
    if (fails(on ? "hdEnable" : "hdDisable")) {
        push_error(HD_INVALID_OPERATION, 0);
        return 0;
    }
    pthread_mutex_lock(&lock);
    int ok = 1;
    switch (cap) {
    case HD_FORCE_OUTPUT:
        force_enabled = on;
        if (!on) memset(committed, 0, sizeof committed);
        break;
    case HD_MAX_FORCE_CLAMPING: clamping = on; break;
    case HD_FORCE_RAMPING: case HD_SOFTWARE_FORCE_LIMIT: case HD_ONE_FRAME_LIMIT: break;
    default: ok = 0;
    }
    pthread_mutex_unlock(&lock);
    if (!ok) push_error(HD_INVALID_ENUM, (int)cap);
    return ok;
}

void hdEnable(HDenum cap) { enable_param(cap, 1); }
void hdDisable(HDenum cap) { enable_param(cap, 0); }

HDboolean hdIsEnabled(HDenum cap) {
    switch (cap) {
    case HD_FORCE_OUTPUT: return (HDboolean)force_enabled;
    case HD_MAX_FORCE_CLAMPING: return (HDboolean)clamping;
    default: return 0;
    }
}

HDenum hdCheckCalibration(void) { return (HDenum)calibration; }

void hdUpdateCalibration(HDenum style) {
    (void)style;
    if (inkwell || calibration == HD_CALIBRATION_NEEDS_UPDATE) calibration = HD_CALIBRATION_OK;
}

/* ---- frames ------------------------------------------------------------------------------ */
void hdBeginFrame(HHD hHD) {
    if (!is_open(hHD)) {
        push_error(HD_BAD_HANDLE, 0);
        return;
    }
    if (frame_depth++ > 0) return;          /* nested: the outer frame's snapshot */
    read_state(&frame);
    frame_force[0] = frame_force[1] = frame_force[2] = 0.0;
    pthread_mutex_lock(&lock);
    int gone = unplugged();
    pthread_mutex_unlock(&lock);
    if (gone) push_error(HD_COMM_ERROR, -2);
}

void hdEndFrame(HHD hHD) {
    if (!is_open(hHD)) {
        push_error(HD_BAD_HANDLE, 0);
        return;
    }
    if (frame_depth == 0) {
        push_error(HD_ILLEGAL_END, 0);
        return;
    }
    if (--frame_depth > 0) return;
    double f[3];
    int finite = 1;
    double norm = 0.0;
    for (int i = 0; i < 3; i++) {
        f[i] = frame_force[i];
        finite = finite && isfinite(f[i]);
        norm += f[i] * f[i];
    }
    norm = sqrt(norm);
    int err = 0;
    if (!finite) {
        err = HD_FORCE_ERROR;
        f[0] = f[1] = f[2] = 0.0;
    } else if (norm > max_force) {
        if (clamping) {
            for (int i = 0; i < 3; i++) f[i] *= max_force / norm;
        } else {
            err = HD_EXCEEDED_MAX_FORCE;
            f[0] = f[1] = f[2] = 0.0;
        }
    }
    pthread_mutex_lock(&lock);
    int on = force_enabled && !unplugged();
    for (int i = 0; i < 3; i++) committed[i] = on ? f[i] : 0.0;
    committed_ns = now_ns();
    commits++;
    pthread_mutex_unlock(&lock);
    if (err) push_error((HDerror)err, 0);
}

/* ---- state -------------------------------------------------------------------------------- */
static void current(Snapshot *s) {
    if (frame_depth > 0) *s = frame;
    else read_state(s);
}

void hdGetDoublev(HDenum pname, HDdouble *out) {
    Snapshot s;
    current(&s);
    switch (pname) {
    case HD_CURRENT_POSITION: memcpy(out, s.pos, sizeof s.pos); return;
    case HD_CURRENT_VELOCITY: memcpy(out, s.vel, sizeof s.vel); return;
    case HD_CURRENT_TRANSFORM:  /* column-major 4 x 4; the stylus held unrotated */
        for (int i = 0; i < 16; i++) out[i] = (i % 5 == 0) ? 1.0 : 0.0;
        out[12] = s.pos[0];
        out[13] = s.pos[1];
        out[14] = s.pos[2];
        if (!isfinite(s.pos[0])) for (int i = 0; i < 12; i++) out[i] = NAN;
        return;
    case HD_CURRENT_ANGULAR_VELOCITY: case HD_CURRENT_JOINT_ANGLES:
    case HD_CURRENT_GIMBAL_ANGLES:
        out[0] = out[1] = out[2] = 0.0;
        return;
    case HD_CURRENT_FORCE:
        memcpy(out, frame_force, sizeof frame_force);
        return;
    case HD_LAST_FORCE:
        pthread_mutex_lock(&lock);
        memcpy(out, committed, sizeof committed);
        pthread_mutex_unlock(&lock);
        return;
    case HD_NOMINAL_MAX_FORCE: out[0] = max_force; return;
    case HD_NOMINAL_MAX_CONTINUOUS_FORCE: out[0] = 0.88; return;
    case HD_INSTANTANEOUS_UPDATE_RATE: case HD_UPDATE_RATE: out[0] = (double)rate; return;
    default: push_error(HD_INVALID_ENUM, (int)pname);
    }
}

void hdGetIntegerv(HDenum pname, HDint *out) {
    Snapshot s;
    current(&s);
    switch (pname) {
    case HD_CURRENT_BUTTONS: *out = s.buttons; return;
    case HD_CURRENT_INKWELL_SWITCH: *out = s.inkwell; return;
    case HD_CURRENT_SAFETY_SWITCH: *out = 1; return;
    case HD_CALIBRATION_STYLE: *out = HD_CALIBRATION_INKWELL; return;
    case HD_INPUT_DOF: *out = 6; return;
    case HD_OUTPUT_DOF: *out = 3; return;
    case HD_UPDATE_RATE: *out = (HDint)rate; return;
    default: push_error(HD_INVALID_ENUM, (int)pname);
    }
}

void hdGetFloatv(HDenum pname, HDfloat *out) {
    HDdouble d[16];
    hdGetDoublev(pname, d);
    int n = pname == HD_CURRENT_TRANSFORM ? 16 : 3;
    for (int i = 0; i < n; i++) out[i] = (HDfloat)d[i];
}

void hdSetDoublev(HDenum pname, const HDdouble *value) {
    if (fails("hdSetDoublev")) {
        push_error(HD_INVALID_OPERATION, 0);
        return;
    }
    if (pname != HD_CURRENT_FORCE) {
        push_error(HD_INVALID_ENUM, (int)pname);
        return;
    }
    if (frame_depth == 0) {         /* forces are set inside a frame only */
        push_error(HD_INVALID_OPERATION, 0);
        return;
    }
    memcpy(frame_force, value, sizeof frame_force);
}

void hdSetFloatv(HDenum pname, const HDfloat *value) {
    HDdouble d[3] = {value[0], value[1], value[2]};
    hdSetDoublev(pname, d);
}

/* ---- scheduler ---------------------------------------------------------------------------- */
static void run_callbacks(void) {
    for (int i = 0; i < n_callbacks;) {
        Callback c = callbacks[i];
        pthread_mutex_unlock(&lock);
        HDCallbackCode code = c.fn(c.data);
        pthread_mutex_lock(&lock);
        /* the list may have changed meanwhile (a callback scheduled another): find it again */
        int j = 0;
        while (j < n_callbacks && callbacks[j].id != c.id) j++;
        if (j == n_callbacks) continue;
        if (code == HD_CALLBACK_DONE) {
            if (callbacks[j].sync) {
                callbacks[j].done = 1;
                pthread_cond_broadcast(&cond);
            }
            memmove(callbacks + j, callbacks + j + 1,
                    (size_t)(n_callbacks - j - 1) * sizeof callbacks[0]);
            n_callbacks--;
            i = j;
        } else {
            i = j + 1;
        }
    }
}

static void *servo(void *arg) {
    (void)arg;
    struct timespec next;
    clock_gettime(CLOCK_MONOTONIC, &next);
    pthread_mutex_lock(&lock);
    while (!stopping) {
        long period = (long)(1000000000L / (long)(rate ? rate : 1000));
        pthread_mutex_unlock(&lock);
        next.tv_nsec += period;
        while (next.tv_nsec >= 1000000000L) {
            next.tv_nsec -= 1000000000L;
            next.tv_sec++;
        }
        while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL) == EINTR) {}
        struct timespec now;
        clock_gettime(CLOCK_MONOTONIC, &now);
        long long late = ((long long)now.tv_sec - next.tv_sec) * 1000000000LL
            + (now.tv_nsec - next.tv_nsec);
        /* Woken late (this thread got no CPU): the device has moved on in real time, one step
         * per period passed, but the callbacks run once, at the newest tick: no burst of
         * callbacks to catch up (as a timerfd read reports its overruns). */
        long long passed = late > 0 ? late / period : 0;
        for (long long i = 0; i < passed; i++) {
            next.tv_nsec += period;
            while (next.tv_nsec >= 1000000000L) {
                next.tv_nsec -= 1000000000L;
                next.tv_sec++;
            }
        }
        pthread_mutex_lock(&lock);
        if (stopping) break;
        tick_ns = now_ns();
        for (long long i = 0; i <= passed; i++) step_device(1.0 / (double)rate);
        skipped += passed;
        if (stall_at < 0 || tick_count < stall_at) run_callbacks();
    }
    /* what never ran: its callers must not wait for ever */
    for (int i = 0; i < n_callbacks; i++) callbacks[i].done = 1;
    n_callbacks = 0;
    pthread_cond_broadcast(&cond);
    pthread_mutex_unlock(&lock);
    return NULL;
}

void hdStartScheduler(void) {
    if (fails("hdStartScheduler")) {
        push_error(HD_TIMER_ERROR, 0);
        return;
    }
    pthread_mutex_lock(&lock);
    if (running) {
        pthread_mutex_unlock(&lock);
        return;
    }
    stopping = 0;
    running = 1;
    pthread_mutex_unlock(&lock);
    if (pthread_create(&thread, NULL, servo, NULL) != 0) {
        pthread_mutex_lock(&lock);
        running = 0;
        pthread_mutex_unlock(&lock);
        push_error(HD_TIMER_ERROR, errno);
    }
}

void hdStopScheduler(void) {
    pthread_mutex_lock(&lock);
    if (!running) {
        pthread_mutex_unlock(&lock);
        return;
    }
    if (pthread_equal(pthread_self(), thread)) {     /* from a callback: cannot join itself */
        pthread_mutex_unlock(&lock);
        push_error(HD_INVALID_OPERATION, 0);
        return;
    }
    stopping = 1;
    pthread_mutex_unlock(&lock);
    pthread_join(thread, NULL);
    pthread_mutex_lock(&lock);
    running = 0;
    pthread_mutex_unlock(&lock);
}

void hdSetSchedulerRate(HDulong nRate) {
    if (nRate < 100 || nRate > 2000) {
        push_error(HD_INVALID_VALUE, (int)nRate);
        return;
    }
    pthread_mutex_lock(&lock);
    rate = nRate;
    pthread_mutex_unlock(&lock);
}

static unsigned long schedule(HDSchedulerCallback fn, void *data, HDushort priority, int sync) {
    pthread_mutex_lock(&lock);
    if (n_callbacks == MAX_CALLBACKS) {
        pthread_mutex_unlock(&lock);
        push_error(HD_SCHEDULER_FULL, 0);
        return 0;
    }
    int at = n_callbacks;
    while (at > 0 && callbacks[at - 1].priority < priority) at--;     /* highest first */
    memmove(callbacks + at + 1, callbacks + at, (size_t)(n_callbacks - at) * sizeof callbacks[0]);
    Callback c = {fn, data, priority, sync, 0, next_id++};
    callbacks[at] = c;
    n_callbacks++;
    pthread_mutex_unlock(&lock);
    return c.id;
}

HDSchedulerHandle hdScheduleAsynchronous(HDSchedulerCallback pCallback, void *pUserData,
                                         HDushort nPriority) {
    return schedule(pCallback, pUserData, nPriority, 0);
}

void hdScheduleSynchronous(HDSchedulerCallback pCallback, void *pUserData, HDushort nPriority) {
    pthread_mutex_lock(&lock);
    int up = running;
    pthread_mutex_unlock(&lock);
    if (!up) {
        push_error(HD_INVALID_OPERATION, 0);
        return;
    }
    unsigned long id = schedule(pCallback, pUserData, nPriority, 1);
    if (!id) return;
    pthread_mutex_lock(&lock);
    for (;;) {
        int j = 0;
        while (j < n_callbacks && callbacks[j].id != id) j++;
        if (j == n_callbacks || callbacks[j].done) break;
        pthread_cond_wait(&cond, &lock);
    }
    pthread_mutex_unlock(&lock);
}

void hdUnschedule(HDSchedulerHandle hHandle) {
    pthread_mutex_lock(&lock);
    for (int j = 0; j < n_callbacks; j++) {
        if (callbacks[j].id == hHandle) {
            memmove(callbacks + j, callbacks + j + 1,
                    (size_t)(n_callbacks - j - 1) * sizeof callbacks[0]);
            n_callbacks--;
            break;
        }
    }
    pthread_mutex_unlock(&lock);
}

HDdouble hdGetSchedulerTimeStamp(void) { return 1.0 / (double)rate; }

/* ---- emulator only ------------------------------------------------------------------------- */
/* The force the motors got at the newest hdEndFrame (N, device axes), its CLOCK_MONOTONIC time
 * (ns) and the number of frames committed so far (returned). */
long long hdEmuApplied(double out[3], long long *t_ns) {
    pthread_mutex_lock(&lock);
    memcpy(out, committed, sizeof committed);
    *t_ns = committed_ns;
    long long n = commits;
    pthread_mutex_unlock(&lock);
    return n;
}

/* Set the buttons (HD_CURRENT_BUTTONS mask) and the inkwell switch while running. */
void hdEmuSetButtons(int mask, int in_inkwell) {
    pthread_mutex_lock(&lock);
    buttons = mask;
    inkwell = in_inkwell;
    pthread_mutex_unlock(&lock);
}

/* CLOCK_MONOTONIC time (ns) at which the newest servo tick began (before the device's step
 * and the callbacks): how long a callback took to be entered, for the cost measurements. */
long long hdEmuTickNs(void) {
    pthread_mutex_lock(&lock);
    long long t = tick_ns;
    pthread_mutex_unlock(&lock);
    return t;
}

/* Servo ticks whose callbacks were skipped because the thread woke late. */
long long hdEmuSkippedTicks(void) {
    pthread_mutex_lock(&lock);
    long long n = skipped;
    pthread_mutex_unlock(&lock);
    return n;
}

/* Servo ticks since hdInitDevice. */
long long hdEmuTicks(void) {
    pthread_mutex_lock(&lock);
    long long n = tick_count;
    pthread_mutex_unlock(&lock);
    return n;
}
