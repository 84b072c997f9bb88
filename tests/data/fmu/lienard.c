/* A Co-Simulation FMU (FMI 2.0) of the Lienard plant of the paper's Section V, for the tests.

       x1' = x2 + x1 + a x1^3 - b x1^5
       x2' = -x1 + u

   Value references (modelDescription.xml): Real x1 = 0, x2 = 1 (outputs, initial exact: x0 is set
   in initialization mode), u = 2 (input), a = 3, b = 4, fail_at = 5 (parameters); Integer n_sub = 6.
   fmi2DoStep integrates over the communication step with n_sub classical Runge-Kutta (RK4) substeps
   per 0.1 s (at least one), the input held; it fails with fmi2Error once t >= fail_at >= 0, which the
   tests use for a failing step.  Every fmi2 function is exported (fmpy resolves them all); those
   the plant does not need return fmi2Error.  Built by tests/data/fmu/build.py with gcc against the FMI 2.0
   headers shipped in fmpy/c-code.
*/
#include <math.h>
#include <stdio.h>
#include <string.h>
#include "fmi2Functions.h"

#define GUID "{5a3c1e7e-2f0b-4d6e-9b1a-7c3d5e1f0a21}"
enum { VR_X1, VR_X2, VR_U, VR_A, VR_B, VR_FAIL_AT, N_REAL };
#define VR_N_SUB 6

typedef struct {
    double r[N_REAL];
    int n_sub;
    double t;
    int init_mode;
    char name[128];
    const fmi2CallbackFunctions *cb;
} Inst;

static void logmsg(Inst *s, fmi2Status st, const char *msg) {
    if (s && s->cb && s->cb->logger)
        s->cb->logger(s->cb->componentEnvironment, s->name, st, st == fmi2OK ? "logAll" : "logStatusError", "%s", msg);
}

static void rhs(const Inst *s, const double *x, double u, double *dx) {
    double x1 = x[0], x1sq = x1 * x1;
    dx[0] = x[1] + x1 + s->r[VR_A] * x1 * x1sq - s->r[VR_B] * x1 * x1sq * x1sq;
    dx[1] = -x1 + u;
}

static void rk4(const Inst *s, double *x, double u, double h) {
    double k1[2], k2[2], k3[2], k4[2], y[2];
    int i;
    rhs(s, x, u, k1);
    for (i = 0; i < 2; i++) y[i] = x[i] + 0.5 * h * k1[i];
    rhs(s, y, u, k2);
    for (i = 0; i < 2; i++) y[i] = x[i] + 0.5 * h * k2[i];
    rhs(s, y, u, k3);
    for (i = 0; i < 2; i++) y[i] = x[i] + h * k3[i];
    rhs(s, y, u, k4);
    for (i = 0; i < 2; i++) x[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
}

const char *fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char *fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n, const fmi2String cats[]) {
    (void)c; (void)on; (void)n; (void)cats;
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid, fmi2String res,
                              const fmi2CallbackFunctions *cb, fmi2Boolean visible, fmi2Boolean loggingOn) {
    Inst *s;
    (void)res; (void)visible; (void)loggingOn;
    if (type != fmi2CoSimulation || !cb || !cb->allocateMemory || strcmp(guid, GUID) != 0) return NULL;
    s = (Inst *)cb->allocateMemory(1, sizeof(Inst));
    if (!s) return NULL;
    s->cb = cb;
    snprintf(s->name, sizeof s->name, "%s", name ? name : "lienard");
    s->r[VR_A] = 1.0 / 3.0;
    s->r[VR_B] = 0.02;
    s->r[VR_FAIL_AT] = -1.0;
    s->n_sub = 100;
    return s;
}

void fmi2FreeInstance(fmi2Component c) {
    Inst *s = (Inst *)c;
    if (s) s->cb->freeMemory(s);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean tolDef, fmi2Real tol, fmi2Real t0,
                               fmi2Boolean stopDef, fmi2Real stop) {
    (void)tolDef; (void)tol; (void)stopDef; (void)stop;
    ((Inst *)c)->t = t0;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) { ((Inst *)c)->init_mode = 1; return fmi2OK; }
fmi2Status fmi2ExitInitializationMode(fmi2Component c) { ((Inst *)c)->init_mode = 0; return fmi2OK; }
fmi2Status fmi2Terminate(fmi2Component c) { (void)c; return fmi2OK; }

fmi2Status fmi2Reset(fmi2Component c) {
    Inst *s = (Inst *)c;
    memset(s->r, 0, sizeof s->r);
    s->r[VR_A] = 1.0 / 3.0;
    s->r[VR_B] = 0.02;
    s->r[VR_FAIL_AT] = -1.0;
    s->n_sub = 100;
    s->t = 0.0;
    s->init_mode = 0;
    return fmi2OK;
}

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Real v[]) {
    Inst *s = (Inst *)c;
    size_t i;
    for (i = 0; i < nvr; i++) {
        if (vr[i] >= N_REAL) { logmsg(s, fmi2Error, "fmi2GetReal: unknown value reference"); return fmi2Error; }
        v[i] = s->r[vr[i]];
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Real v[]) {
    Inst *s = (Inst *)c;
    size_t i;
    for (i = 0; i < nvr; i++) {
        if (vr[i] >= N_REAL) { logmsg(s, fmi2Error, "fmi2SetReal: unknown value reference"); return fmi2Error; }
        s->r[vr[i]] = v[i];
    }
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, fmi2Integer v[]) {
    Inst *s = (Inst *)c;
    size_t i;
    for (i = 0; i < nvr; i++) {
        if (vr[i] != VR_N_SUB) return fmi2Error;
        v[i] = s->n_sub;
    }
    return fmi2OK;
}

fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t nvr, const fmi2Integer v[]) {
    Inst *s = (Inst *)c;
    size_t i;
    for (i = 0; i < nvr; i++) {
        if (vr[i] != VR_N_SUB || v[i] < 1) { logmsg(s, fmi2Error, "fmi2SetInteger: n_sub must be >= 1"); return fmi2Error; }
        s->n_sub = v[i];
    }
    return fmi2OK;
}

fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2Boolean v[]) {
    (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK;
}
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, fmi2String v[]) {
    (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK;
}
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2Boolean v[]) {
    (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK;
}
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t n, const fmi2String v[]) {
    (void)c; (void)vr; (void)v; return n ? fmi2Error : fmi2OK;
}

fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate *st) { (void)c; (void)st; return fmi2Error; }
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate st) { (void)c; (void)st; return fmi2Error; }
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate *st) { (void)c; (void)st; return fmi2Error; }
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate st, size_t *n) {
    (void)c; (void)st; (void)n; return fmi2Error;
}
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate st, fmi2Byte b[], size_t n) {
    (void)c; (void)st; (void)b; (void)n; return fmi2Error;
}
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n, fmi2FMUstate *st) {
    (void)c; (void)b; (void)n; (void)st; return fmi2Error;
}
fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[], size_t nu,
                                        const fmi2ValueReference k[], size_t nk, const fmi2Real dk[], fmi2Real du[]) {
    (void)c; (void)u; (void)nu; (void)k; (void)nk; (void)dk; (void)du; return fmi2Error;
}

fmi2Status fmi2SetRealInputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                       const fmi2Integer o[], const fmi2Real v[]) {
    (void)c; (void)vr; (void)n; (void)o; (void)v; return fmi2Error;
}
fmi2Status fmi2GetRealOutputDerivatives(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                                        const fmi2Integer o[], fmi2Real v[]) {
    (void)c; (void)vr; (void)n; (void)o; (void)v; return fmi2Error;
}

fmi2Status fmi2DoStep(fmi2Component c, fmi2Real t, fmi2Real dt, fmi2Boolean noSetPrior) {
    Inst *s = (Inst *)c;
    int k, n;
    double h;
    char msg[160];
    (void)noSetPrior;
    if (s->r[VR_FAIL_AT] >= 0.0 && t >= s->r[VR_FAIL_AT]) {
        snprintf(msg, sizeof msg, "the plant broke at t = %g s (fail_at = %g)", t, s->r[VR_FAIL_AT]);
        logmsg(s, fmi2Error, msg);
        return fmi2Error;
    }
    if (!(dt > 0.0)) return fmi2Error;
    n = (int)ceil(dt / 0.1 * s->n_sub - 1e-9);
    if (n < 1) n = 1;
    h = dt / n;
    for (k = 0; k < n; k++) rk4(s, s->r, s->r[VR_U], h);
    s->t = t + dt;
    return fmi2OK;
}

fmi2Status fmi2CancelStep(fmi2Component c) { (void)c; return fmi2Error; }
fmi2Status fmi2GetStatus(fmi2Component c, const fmi2StatusKind k, fmi2Status *v) { (void)c; (void)k; (void)v; return fmi2Error; }
fmi2Status fmi2GetRealStatus(fmi2Component c, const fmi2StatusKind k, fmi2Real *v) {
    Inst *s = (Inst *)c;
    if (k != fmi2LastSuccessfulTime) return fmi2Error;
    *v = s->t;
    return fmi2OK;
}
fmi2Status fmi2GetIntegerStatus(fmi2Component c, const fmi2StatusKind k, fmi2Integer *v) { (void)c; (void)k; (void)v; return fmi2Error; }
fmi2Status fmi2GetBooleanStatus(fmi2Component c, const fmi2StatusKind k, fmi2Boolean *v) { (void)c; (void)k; (void)v; return fmi2Error; }
fmi2Status fmi2GetStringStatus(fmi2Component c, const fmi2StatusKind k, fmi2String *v) { (void)c; (void)k; (void)v; return fmi2Error; }
