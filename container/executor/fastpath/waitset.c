/* WaitSet: an rcl wait set over fixed entities, filled, waited on and read in one call (see module.c). */
#include "fastpath.h"

/* ------------------------------------------------------------------------ */
enum { WS_SUBSCRIPTIONS, WS_GUARDS, WS_TIMERS, WS_CLIENTS, WS_SERVICES, WS_EVENTS, WS_KINDS };

typedef struct {
  PyObject_HEAD
  rcl_wait_set_t wait_set;
  int initialised;
  int waiting;                 /* a thread is in rcl_wait without the GIL: close() must not free under it */
  Held context;                /* rcl_context_t the wait set was made in */
  Held * entities[WS_KINDS];   /* each kind's handles, held (what the wait set points at) */
  size_t counts[WS_KINDS];
  NotifierObject * notifier; /* told when each wait ends at the latest, or NULL */
  HandoffObject * handoff;   /* the loop's hand-overs to workers (with a notifier only), or NULL */
} WaitSetObject;

static int WaitSet_init(WaitSetObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {
    "context", "subscriptions", "guard_conditions", "timers", "clients", "services", "events", "notifier",
    "handoff", NULL};
  PyObject * context;
  PyObject * notifier = Py_None;
  PyObject * handoff = Py_None;
  PyObject * given[WS_KINDS] = {NULL, NULL, NULL, NULL, NULL, NULL};
  PyObject * empty;
  rcl_ret_t ret;
  int kind;
  if (self->initialised || self->context.handle != NULL) {
    PyErr_SetString(PyExc_RuntimeError, "WaitSet is initialised once");
    return -1;
  }
  if (!PyArg_ParseTupleAndKeywords(
      args, kwargs, "O|$OOOOOOOO", keywords, &context, &given[WS_SUBSCRIPTIONS], &given[WS_GUARDS],
      &given[WS_TIMERS], &given[WS_CLIENTS], &given[WS_SERVICES], &given[WS_EVENTS], &notifier, &handoff))
  {
    return -1;
  }
  if (notifier != Py_None && !PyObject_TypeCheck(notifier, &NotifierType)) {
    PyErr_SetString(PyExc_TypeError, "notifier must be a Notifier or None");
    return -1;
  }
  if (handoff != Py_None && !PyObject_TypeCheck(handoff, &HandoffType)) {
    PyErr_SetString(PyExc_TypeError, "handoff must be a Handoff or None");
    return -1;
  }
  empty = PyTuple_New(0);
  if (empty == NULL || held_enter(&self->context, context) < 0) {
    Py_XDECREF(empty);
    return -1;
  }
  for (kind = 0; kind < WS_KINDS; ++kind) {
    if (held_enter_all(given[kind] != NULL ? given[kind] : empty, &self->entities[kind], &self->counts[kind]) < 0) {
      while (--kind >= 0) {
        held_exit_all(&self->entities[kind], &self->counts[kind]);
      }
      held_exit(&self->context);
      Py_DECREF(empty);
      return -1;
    }
  }
  Py_DECREF(empty);
  self->wait_set = rcl_get_zero_initialized_wait_set();
  ret = rcl_wait_set_init(
    &self->wait_set, self->counts[WS_SUBSCRIPTIONS], self->counts[WS_GUARDS], self->counts[WS_TIMERS],
    self->counts[WS_CLIENTS], self->counts[WS_SERVICES], self->counts[WS_EVENTS],
    (rcl_context_t *)self->context.pointer, rcl_get_default_allocator());
  if (ret != RCL_RET_OK) {
    rcl_failed("rcl_wait_set_init");
    for (kind = WS_KINDS - 1; kind >= 0; --kind) {
      held_exit_all(&self->entities[kind], &self->counts[kind]);
    }
    held_exit(&self->context);
    return -1;
  }
  if (notifier != Py_None) {
    self->notifier = (NotifierObject *)Py_NewRef(notifier);
    if (handoff != Py_None) {
      self->handoff = (HandoffObject *)Py_NewRef(handoff);
    }
  }
  self->initialised = 1;
  return 0;
}

/* The rcl wait set goes (it points at the entities), then the handles, the context last. */
static void waitset_close(WaitSetObject * self)
{
  int kind;
  if (self->initialised) {
    self->initialised = 0;
    if (rcl_wait_set_fini(&self->wait_set) != RCL_RET_OK) {
      rcl_reset_error();
    }
  }
  for (kind = WS_KINDS - 1; kind >= 0; --kind) {
    held_exit_all(&self->entities[kind], &self->counts[kind]);
  }
  held_exit(&self->context);
}

static void WaitSet_dealloc(WaitSetObject * self)
{
  waitset_close(self);
  Py_XDECREF(self->notifier);
  Py_XDECREF(self->handoff);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject * WaitSet_close(WaitSetObject * self, PyObject * Py_UNUSED(ignored))
{
  if (self->waiting) {
    PyErr_SetString(PyExc_RuntimeError, "WaitSet.close() while a thread waits in it: wake it first");
    return NULL;
  }
  waitset_close(self);
  Py_RETURN_NONE;
}

static rcl_ret_t fill(WaitSetObject * self)
{
  rcl_wait_set_t * ws = &self->wait_set;
  rcl_ret_t ret = rcl_wait_set_clear(ws);
  size_t i;
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_SUBSCRIPTIONS]; ++i) {
    ret = rcl_wait_set_add_subscription(ws, self->entities[WS_SUBSCRIPTIONS][i].pointer, NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_GUARDS]; ++i) {
    ret = rcl_wait_set_add_guard_condition(ws, self->entities[WS_GUARDS][i].pointer, NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_TIMERS]; ++i) {
    ret = rcl_wait_set_add_timer(ws, self->entities[WS_TIMERS][i].pointer, NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_CLIENTS]; ++i) {
    ret = rcl_wait_set_add_client(ws, self->entities[WS_CLIENTS][i].pointer, NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_SERVICES]; ++i) {
    ret = rcl_wait_set_add_service(ws, self->entities[WS_SERVICES][i].pointer, NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_EVENTS]; ++i) {
    ret = rcl_wait_set_add_event(ws, self->entities[WS_EVENTS][i].pointer, NULL);
  }
  return ret;
}

/* The ready entities of one kind, as a list of addresses. */
static PyObject * ready_of(const void * const * slots, size_t count)
{
  PyObject * list = PyList_New(0);
  size_t i;
  if (list == NULL) {
    return NULL;
  }
  for (i = 0; i < count; ++i) {
    if (slots[i] != NULL) {
      PyObject * address = PyLong_FromUnsignedLongLong((unsigned long long)(uintptr_t)slots[i]);
      if (address == NULL || PyList_Append(list, address) < 0) {
        Py_XDECREF(address);
        Py_DECREF(list);
        return NULL;
      }
      Py_DECREF(address);
    }
  }
  return list;
}

/* When an rcl_wait with this timeout (ns, negative: none) returns at the
 * latest, on CLOCK_MONOTONIC: rcl_wait's own rule (the timeout or the soonest
 * timer, skipping cancelled timers and ROS-time timers under a time
 * override, which only their clock's jumps wake); LLONG_MAX when unknown. */
static long long wake_deadline(WaitSetObject * self, long long timeout)
{
  long long soonest = timeout >= 0 ? timeout : LLONG_MAX;
  size_t i;
  for (i = 0; i < self->counts[WS_TIMERS]; ++i) {
    const rcl_timer_t * timer = self->entities[WS_TIMERS][i].pointer;
    rcl_clock_t * clock = NULL;
    int64_t until = 0;
    rcl_ret_t ret = rcl_timer_clock((rcl_timer_t *)timer, &clock);
    if (ret == RCL_RET_OK && clock->type == RCL_ROS_TIME) {
      bool overridden = false;
      ret = rcl_is_enabled_ros_time_override(clock, &overridden);
      if (ret == RCL_RET_OK && overridden) {
        continue;
      }
    }
    if (ret == RCL_RET_OK) {
      ret = rcl_timer_get_time_until_next_call(timer, &until);
    }
    if (ret == RCL_RET_TIMER_CANCELED) {
      rcl_reset_error();
      continue;
    }
    if (ret != RCL_RET_OK) {
      rcl_reset_error();
      return LLONG_MAX;
    }
    if (until < soonest) {
      soonest = until > 0 ? until : 0;
    }
  }
  return soonest == LLONG_MAX ? LLONG_MAX : monotonic_ns() + soonest;
}

/* The longest a poll may hold the GIL in rcl_wait, should its guard
 * condition not be in the wait set after all (destroyed at shutdown).
 *
 * A safety bound (commit 1dbf0f2, tested both ways in test_fastpath.py),
 * not a tuned figure: no measurement of the value is recorded. A poll
 * returns at once on its triggered guard; only a missing guard makes it
 * wait, asleep in rcl_wait (not spinning), holding the GIL 1 ms at most:
 * the same on one CPU as on two. */
#define POLL_HOLD_MAX_NS 1000000LL

long long poll_timeout(long long timeout)
{
  return timeout < 0 || timeout > POLL_HOLD_MAX_NS ? POLL_HOLD_MAX_NS : timeout;
}

/* wait(timeout_ns, poll=False). A poll (a wait whose guard condition is
 * already triggered, so rcl_wait returns at once) keeps the GIL. Released
 * for those few microseconds, once a millisecond while a chain of callbacks
 * runs, it wakes a thread waiting for it (a lane's worker, the watchdog),
 * which loses the race to take it back and starts its wait for a forced
 * switch (sys.getswitchinterval()) all over again: a plain 20 Hz timer beside
 * a busy chain ran 0-12 times in 4 s instead of 80. Kept, the waiting
 * thread's switch interval runs out and CPython hands the GIL over. A poll
 * waits at most POLL_HOLD_MAX_NS, whatever its timeout. */
static PyObject * WaitSet_wait(WaitSetObject * self, PyObject * const * args, Py_ssize_t nargs)
{
  long long timeout;
  int poll = 0;
  rcl_wait_set_t * ws = &self->wait_set;
  rcl_ret_t ret;
  if (nargs < 1 || nargs > 2) {
    PyErr_SetString(PyExc_TypeError, "wait(timeout_ns, poll=False)");
    return NULL;
  }
  timeout = PyLong_AsLongLong(args[0]);
  if (timeout == -1 && PyErr_Occurred()) {
    return NULL;
  }
  if (nargs == 2 && (poll = PyObject_IsTrue(args[1])) < 0) {
    return NULL;
  }
  if (!self->initialised) {
    PyErr_SetString(PyExc_RuntimeError, "WaitSet not initialised, or closed");
    return NULL;
  }
  ret = fill(self);
  if (ret == RCL_RET_OK && poll) {
    ret = rcl_wait(ws, (int64_t)poll_timeout(timeout));
  } else if (ret == RCL_RET_OK) {
    /* Only a carrier's publish reads it (on_event). */
    NotifierObject * told = atomic_load(&carriers_exist) ? self->notifier : NULL;
    HandoffObject * handoff = self->handoff;
    self->waiting = 1;
    Py_BEGIN_ALLOW_THREADS
    /* Plain work was handed to workers and runs: its answer (a response, a
     * message) usually comes within microseconds, and waking this thread's
     * idle core for it costs more. So the thread stays awake for it first,
     * no later than the wait would end (its timeout, its soonest timer): no
     * timer fires later for it. An answer that comes disarmed the notifier
     * and triggered its guard: rcl_wait then returns at once. Never with
     * one CPU (the Handoff's spin is off: see handoff.c), where the worker
     * could only answer once this thread stopped spinning. */
    int linger = handoff != NULL && timeout != 0 && handoff_may_linger(handoff);
    long long by = told != NULL || linger ? wake_deadline(self, timeout) : LLONG_MAX;
    if (told != NULL) {
      /* Set before lingering: a carrier's publish wakes no one meanwhile either. */
      atomic_store(&told->wake_by, by);
    }
    if (handoff != NULL) {
      handoff_loop_free(handoff, 1);
    }
    if (linger) {
      long long from = monotonic_ns();
      if (by == LLONG_MAX || by > from) { /* not when a timer is due already */
        handoff_loop_linger(handoff, &self->notifier->armed, by == LLONG_MAX ? -1 : by - from);
        if (timeout > 0) {
          long long spent = monotonic_ns() - from;
          timeout = timeout > spent ? timeout - spent : 0;
        }
      }
    }
    ret = rcl_wait(ws, (int64_t)timeout);
    if (told != NULL) {
      atomic_store(&told->wake_by, LLONG_MAX);
    }
    if (handoff != NULL) {
      handoff_loop_free(handoff, 0);
    }
    Py_END_ALLOW_THREADS
    self->waiting = 0;
  }
  if (ret == RCL_RET_TIMEOUT) {
    /* Nothing ready: rcl cleared every slot. */
    return Py_BuildValue("()");
  }
  if (ret != RCL_RET_OK) {
    return rcl_failed("rcl_wait");
  }
  return Py_BuildValue(
    "(NNNNNN)",
    ready_of((const void * const *)ws->subscriptions, ws->size_of_subscriptions),
    ready_of((const void * const *)ws->guard_conditions, ws->size_of_guard_conditions),
    ready_of((const void * const *)ws->timers, ws->size_of_timers),
    ready_of((const void * const *)ws->clients, ws->size_of_clients),
    ready_of((const void * const *)ws->services, ws->size_of_services),
    ready_of((const void * const *)ws->events, ws->size_of_events));
}

static PyMethodDef WaitSet_methods[] = {
  {"wait", (PyCFunction)(void (*)(void))WaitSet_wait, METH_FASTCALL,
   "wait(timeout_ns, poll=False) -> () on timeout, else the ready addresses: (subscriptions, guard_conditions, "
   "timers, clients, services, events)"},
  {"close", (PyCFunction)WaitSet_close, METH_NOARGS, "close() -> None: let every handle go"},
  {NULL, NULL, 0, NULL},
};

PyTypeObject WaitSetType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.WaitSet",
  .tp_doc = "An rcl wait set over fixed entities: fill, wait and read in one call.",
  .tp_basicsize = sizeof(WaitSetObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)WaitSet_init,
  .tp_dealloc = (destructor)WaitSet_dealloc,
  .tp_methods = WaitSet_methods,
};

