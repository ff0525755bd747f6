/* _fastpath: the executor's hot path in C: readiness and takes.
 *
 * Notifier: event-driven readiness for rcl subscriptions, clients and services.
 *
 * Why: a wait set is level-triggered and rebuilt (attached, detached) on
 * every rcl_wait, and a message published by one node of this process to
 * another is only found by the next wait. rmw offers a per-entity "new data"
 * callback instead, which Fast DDS calls in the publishing thread for a
 * reader of the same process, or in its receive thread for a remote writer.
 * This module registers that callback, records which entities became ready,
 * and triggers one rcl guard condition only while the executor's thread is
 * actually asleep in rcl_wait (armed). The executor then takes what is
 * ready without another wait: a ping-pong between two nodes of one process
 * never enters rcl_wait at all.
 *
 * Entities are identified by their rcl handle's address, which rclpy exposes
 * as ``handle.pointer``. The caller keeps each handle alive (held) from
 * ``watch`` until ``unwatch``: after ``unwatch`` returns no callback runs
 * for it any more (rmw serialises setting and calling the callback).
 *
 * WaitSet: an rcl wait set over entities given once (by handle address),
 * filled, waited on and read in one call: rclpy's wait set takes a call per
 * entity to fill and one per kind to read, on every wait.
 *
 * Taker: rcl_take of one subscription into a C message kept across takes,
 * converted with the message type's own rosidl capsules; what rclpy's
 * take_message does, without rebuilding the message, the pybind11 call
 * and the message-info dictionary nobody asked for.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <pthread.h>
#include <stdatomic.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include <rcl/client.h>
#include <rcl/error_handling.h>
#include <rcl/event.h>
#include <rcl/guard_condition.h>
#include <rcl/service.h>
#include <rcl/subscription.h>
#include <rcl/timer.h>
#include <rcl/wait.h>
#include <rmw/types.h>

enum { KIND_SUBSCRIPTION = 0, KIND_CLIENT = 1, KIND_SERVICE = 2, KIND_EVENT = 3 };

/* The event count that means "take until nothing is left". */
#define DRAIN ((size_t)1 << 30)

typedef struct Slot {
  struct NotifierObject * owner;
  uintptr_t key;
  int kind;
  int queued;    /* under owner->lock */
  int plain;     /* its callback runs on a worker thread: carry() hands it out */
  size_t count;  /* events since last ready(), under owner->lock */
  struct Slot * next;
} Slot;

typedef struct NotifierObject {
  PyObject_HEAD
  pthread_mutex_t lock;
  atomic_int armed;
  atomic_int pending;
  atomic_int plain_pending;      /* queued slots that are plain */
  rcl_guard_condition_t * guard; /* under lock */
  Slot * slots;                  /* touched by the owning Python thread only */
  Slot ** ready;                 /* under lock */
  size_t nready;
  size_t capacity;
  atomic_ulong triggers;
} NotifierObject;

static void trigger(rcl_guard_condition_t * guard)
{
  if (rcl_trigger_guard_condition(guard) != RCL_RET_OK) {
    rcl_reset_error(); /* a guard being destroyed: the waiter is going away too */
  }
}

static void on_event(const void * user_data, size_t number_of_events)
{
  Slot * slot = (Slot *)user_data;
  NotifierObject * self;
  if (slot == NULL || number_of_events == 0) {
    return;
  }
  self = slot->owner;
  pthread_mutex_lock(&self->lock);
  slot->count = slot->count + number_of_events < DRAIN ? slot->count + number_of_events : DRAIN;
  if (!slot->queued) {
    if (self->nready == self->capacity) {
      size_t capacity = self->capacity ? self->capacity * 2 : 16;
      Slot ** grown = realloc(self->ready, capacity * sizeof(Slot *));
      if (grown == NULL) {
        /* Out of memory: the entity is still ready in rmw; wake the thread,
         * whose next full poll takes it. */
        atomic_store(&self->pending, 1);
        if (self->guard != NULL) {
          trigger(self->guard);
        }
        pthread_mutex_unlock(&self->lock);
        return;
      }
      self->ready = grown;
      self->capacity = capacity;
    }
    self->ready[self->nready++] = slot;
    slot->queued = 1;
    if (slot->plain) {
      atomic_fetch_add(&self->plain_pending, 1);
    }
  }
  pthread_mutex_unlock(&self->lock);
  /* Dekker with arm(): either the waiter sees pending, or we see armed. */
  atomic_store(&self->pending, 1);
  if (atomic_exchange(&self->armed, 0)) {
    pthread_mutex_lock(&self->lock);
    if (self->guard != NULL) {
      atomic_fetch_add(&self->triggers, 1);
      trigger(self->guard);
    }
    pthread_mutex_unlock(&self->lock);
  }
}

static rcl_ret_t set_callback(int kind, uintptr_t key, rcl_event_callback_t callback, const void * data)
{
  switch (kind) {
    case KIND_SUBSCRIPTION:
      return rcl_subscription_set_on_new_message_callback((const rcl_subscription_t *)key, callback, data);
    case KIND_CLIENT:
      return rcl_client_set_on_new_response_callback((const rcl_client_t *)key, callback, data);
    case KIND_SERVICE:
      return rcl_service_set_on_new_request_callback((const rcl_service_t *)key, callback, data);
    default:
      return rcl_event_set_callback((const rcl_event_t *)key, callback, data);
  }
}

static int Notifier_init(NotifierObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"guard", NULL};
  unsigned long long guard;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "K", keywords, &guard)) {
    return -1;
  }
  if (guard == 0) {
    PyErr_SetString(PyExc_ValueError, "guard must be an rcl guard condition's address");
    return -1;
  }
  pthread_mutex_lock(&self->lock);
  self->guard = (rcl_guard_condition_t *)(uintptr_t)guard;
  pthread_mutex_unlock(&self->lock);
  return 0;
}

static PyObject * Notifier_new(PyTypeObject * type, PyObject * args, PyObject * kwargs)
{
  NotifierObject * self = (NotifierObject *)type->tp_alloc(type, 0);
  (void)args;
  (void)kwargs;
  if (self == NULL) {
    return NULL;
  }
  pthread_mutex_init(&self->lock, NULL);
  atomic_init(&self->armed, 0);
  atomic_init(&self->pending, 0);
  atomic_init(&self->plain_pending, 0);
  atomic_init(&self->triggers, 0);
  self->guard = NULL;
  self->slots = NULL;
  self->ready = NULL;
  self->nready = self->capacity = 0;
  return (PyObject *)self;
}

static void Notifier_dealloc(NotifierObject * self)
{
  /* Slots still watched are leaked on purpose: rmw may still call into
   * them if their entity lives on. Their owner pointer must then stay
   * valid too, so a notifier with watched slots is never freed. */
  if (self->slots != NULL) {
    return;
  }
  free(self->ready);
  pthread_mutex_destroy(&self->lock);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static Slot * find(NotifierObject * self, uintptr_t key, Slot *** link)
{
  Slot ** at = &self->slots;
  while (*at != NULL && (*at)->key != key) {
    at = &(*at)->next;
  }
  if (link != NULL) {
    *link = at;
  }
  return *at;
}

static PyObject * Notifier_watch(NotifierObject * self, PyObject * args)
{
  unsigned long long key;
  int kind;
  int plain = 0;
  Slot * slot;
  rcl_ret_t ret;
  if (!PyArg_ParseTuple(args, "Ki|p", &key, &kind, &plain)) {
    return NULL;
  }
  if (key == 0 || kind < KIND_SUBSCRIPTION || kind > KIND_EVENT) {
    PyErr_SetString(PyExc_ValueError, "watch() needs a handle address and a known kind");
    return NULL;
  }
  if (find(self, (uintptr_t)key, NULL) != NULL) {
    Py_RETURN_FALSE;
  }
  slot = calloc(1, sizeof(Slot));
  if (slot == NULL) {
    return PyErr_NoMemory();
  }
  slot->owner = self;
  slot->key = (uintptr_t)key;
  slot->kind = kind;
  slot->plain = plain;
  slot->next = self->slots;
  self->slots = slot;
  /* rmw calls back at once, in this thread, if data is already waiting:
   * our lock must not be held here. */
  Py_BEGIN_ALLOW_THREADS
  ret = set_callback(kind, slot->key, on_event, slot);
  Py_END_ALLOW_THREADS
  if (ret != RCL_RET_OK) {
    self->slots = slot->next;
    free(slot);
    rcl_reset_error();
    PyErr_Format(
      ret == RCL_RET_UNSUPPORTED ? PyExc_NotImplementedError : PyExc_RuntimeError,
      "rmw refused a new-data callback (rcl error %d)", (int)ret);
    return NULL;
  }
  /* rmw reports only data it has not reported before: what it reported to
   * an earlier watch of this entity and nobody took would never be named
   * again. A fresh watch therefore asks for everything waiting once. Not
   * for a QoS event: taking one that did not fire returns a status anyway
   * (a bogus "incompatible QoS" warning), and rmw reports a pending one. */
  if (kind != KIND_EVENT) {
    on_event(slot, DRAIN);
  }
  Py_RETURN_TRUE;
}

static PyObject * Notifier_unwatch(NotifierObject * self, PyObject * arg)
{
  unsigned long long key = PyLong_AsUnsignedLongLong(arg);
  Slot ** link;
  Slot * slot;
  rcl_ret_t ret;
  size_t i;
  if (PyErr_Occurred()) {
    return NULL;
  }
  slot = find(self, (uintptr_t)key, &link);
  if (slot == NULL) {
    Py_RETURN_FALSE;
  }
  Py_BEGIN_ALLOW_THREADS
  ret = set_callback(slot->kind, slot->key, NULL, NULL);
  Py_END_ALLOW_THREADS
  if (ret != RCL_RET_OK) {
    rcl_reset_error();
  }
  *link = slot->next;
  pthread_mutex_lock(&self->lock);
  for (i = 0; i < self->nready; ++i) {
    if (self->ready[i] == slot) {
      memmove(&self->ready[i], &self->ready[i + 1], (self->nready - i - 1) * sizeof(Slot *));
      --self->nready;
      if (slot->plain) {
        atomic_fetch_sub(&self->plain_pending, 1);
      }
      break;
    }
  }
  pthread_mutex_unlock(&self->lock);
  free(slot);
  Py_RETURN_TRUE;
}

/* Called just before rcl_wait: returns True when something is already
 * ready (then the caller must not block). Otherwise stays armed until the
 * first new-data callback triggers the guard, or until disarm(). */
static PyObject * Notifier_arm(NotifierObject * self, PyObject * Py_UNUSED(ignored))
{
  atomic_store(&self->armed, 1);
  if (atomic_load(&self->pending)) {
    atomic_store(&self->armed, 0);
    Py_RETURN_TRUE;
  }
  Py_RETURN_FALSE;
}

static PyObject * Notifier_disarm(NotifierObject * self, PyObject * Py_UNUSED(ignored))
{
  atomic_store(&self->armed, 0);
  Py_RETURN_NONE;
}

static PyObject * Notifier_pending(NotifierObject * self, PyObject * Py_UNUSED(ignored))
{
  return PyBool_FromLong(atomic_load(&self->pending));
}

/* The keys of the entities that became ready since the last call, oldest
 * first; each appears once however many events it had. */
static PyObject * Notifier_ready(NotifierObject * self, PyObject * Py_UNUSED(ignored))
{
  PyObject * list;
  size_t i;
  if (!atomic_load(&self->pending)) {
    return PyList_New(0);
  }
  pthread_mutex_lock(&self->lock);
  atomic_store(&self->pending, 0);
  list = PyList_New((Py_ssize_t)self->nready);
  if (list != NULL) {
    for (i = 0; i < self->nready; ++i) {
      PyObject * item = Py_BuildValue(
        "(Kn)", (unsigned long long)self->ready[i]->key, (Py_ssize_t)self->ready[i]->count);
      if (item == NULL) {
        Py_CLEAR(list);
        break;
      }
      PyList_SET_ITEM(list, (Py_ssize_t)i, item);
    }
    if (list != NULL) {
      for (i = 0; i < self->nready; ++i) {
        self->ready[i]->queued = 0;
        self->ready[i]->count = 0;
      }
      self->nready = 0;
      atomic_store(&self->plain_pending, 0);
    }
  }
  if (list == NULL) {
    atomic_store(&self->pending, 1);
  }
  pthread_mutex_unlock(&self->lock);
  return list;
}

/* Like ready(), for plain slots only; the others stay queued for ready().
 * A worker thread that just ran a plain callback takes what that callback's
 * publishes made ready for other plain callbacks, and runs the next one
 * itself instead of waking another thread. */
static PyObject * Notifier_carry(NotifierObject * self, PyObject * Py_UNUSED(ignored))
{
  PyObject * list;
  size_t i;
  size_t kept = 0;
  if (!atomic_load(&self->plain_pending)) {
    return PyList_New(0);
  }
  list = PyList_New(0);
  if (list == NULL) {
    return NULL;
  }
  pthread_mutex_lock(&self->lock);
  for (i = 0; i < self->nready; ++i) {
    Slot * slot = self->ready[i];
    if (!slot->plain) {
      self->ready[kept++] = slot;
      continue;
    }
    PyObject * item = Py_BuildValue("(Kn)", (unsigned long long)slot->key, (Py_ssize_t)slot->count);
    if (item == NULL || PyList_Append(list, item) < 0) {
      Py_XDECREF(item);
      /* Leave this and the rest queued for ready(). */
      for (; i < self->nready; ++i) {
        self->ready[kept++] = self->ready[i];
      }
      Py_CLEAR(list);
      break;
    }
    Py_DECREF(item);
    slot->queued = 0;
    slot->count = 0;
    atomic_fetch_sub(&self->plain_pending, 1);
  }
  self->nready = kept;
  if (kept == 0) {
    atomic_store(&self->pending, 0);
  }
  pthread_mutex_unlock(&self->lock);
  return list;
}

/* Stop triggering the guard (it is about to be destroyed). */
static PyObject * Notifier_close(NotifierObject * self, PyObject * Py_UNUSED(ignored))
{
  pthread_mutex_lock(&self->lock);
  self->guard = NULL;
  pthread_mutex_unlock(&self->lock);
  Py_RETURN_NONE;
}

static PyObject * Notifier_get_triggers(NotifierObject * self, void * Py_UNUSED(closure))
{
  return PyLong_FromUnsignedLong(atomic_load(&self->triggers));
}

static PyObject * Notifier_get_watched(NotifierObject * self, void * Py_UNUSED(closure))
{
  Py_ssize_t count = 0;
  Slot * slot;
  for (slot = self->slots; slot != NULL; slot = slot->next) {
    ++count;
  }
  return PyLong_FromSsize_t(count);
}

static PyMethodDef Notifier_methods[] = {
  {"watch", (PyCFunction)Notifier_watch, METH_VARARGS,
   "watch(pointer, kind, plain=False) -> bool: report new data of this rcl entity (False: already watched)."},
  {"unwatch", (PyCFunction)Notifier_unwatch, METH_O,
   "unwatch(pointer) -> bool: stop; no callback for it runs once this returns."},
  {"arm", (PyCFunction)Notifier_arm, METH_NOARGS,
   "arm() -> bool: about to wait; True if something is ready already (do not block)."},
  {"disarm", (PyCFunction)Notifier_disarm, METH_NOARGS, "disarm(): back from the wait."},
  {"pending", (PyCFunction)Notifier_pending, METH_NOARGS, "pending() -> bool: something is ready."},
  {"carry", (PyCFunction)Notifier_carry, METH_NOARGS,
   "carry() -> [(address, count)]: what ready() would give, of the plain slots only."},
  {"ready", (PyCFunction)Notifier_ready, METH_NOARGS,
   "ready() -> list[tuple[int, int]]: (entity, events) that became ready since the last call."},
  {"close", (PyCFunction)Notifier_close, METH_NOARGS, "close(): never trigger the guard again."},
  {NULL, NULL, 0, NULL},
};

static PyGetSetDef Notifier_getset[] = {
  {"triggers", (getter)Notifier_get_triggers, NULL, "How often a callback woke the waiter.", NULL},
  {"watched", (getter)Notifier_get_watched, NULL, "How many entities are watched.", NULL},
  {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject NotifierType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Notifier",
  .tp_doc = "New-data callbacks of rcl entities, turned into a ready list and one guard trigger.",
  .tp_basicsize = sizeof(NotifierObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = Notifier_new,
  .tp_init = (initproc)Notifier_init,
  .tp_dealloc = (destructor)Notifier_dealloc,
  .tp_methods = Notifier_methods,
  .tp_getset = Notifier_getset,
};

/* ------------------------------------------------------------------------ */
enum { WS_SUBSCRIPTIONS, WS_GUARDS, WS_TIMERS, WS_CLIENTS, WS_SERVICES, WS_EVENTS, WS_KINDS };

typedef struct {
  PyObject_HEAD
  rcl_wait_set_t wait_set;
  int initialised;
  void ** entities[WS_KINDS];
  size_t counts[WS_KINDS];
} WaitSetObject;

static int addresses(PyObject * sequence, void *** out, size_t * count)
{
  PyObject * fast = PySequence_Fast(sequence, "entities must be a sequence of handle addresses");
  Py_ssize_t i, n;
  if (fast == NULL) {
    return -1;
  }
  n = PySequence_Fast_GET_SIZE(fast);
  *out = calloc(n > 0 ? (size_t)n : 1, sizeof(void *));
  if (*out == NULL) {
    Py_DECREF(fast);
    PyErr_NoMemory();
    return -1;
  }
  for (i = 0; i < n; ++i) {
    unsigned long long address = PyLong_AsUnsignedLongLong(PySequence_Fast_GET_ITEM(fast, i));
    if (PyErr_Occurred()) {
      Py_DECREF(fast);
      return -1;
    }
    if (address == 0) {
      Py_DECREF(fast);
      PyErr_SetString(PyExc_ValueError, "a handle address is 0");
      return -1;
    }
    (*out)[i] = (void *)(uintptr_t)address;
  }
  *count = (size_t)n;
  Py_DECREF(fast);
  return 0;
}

static int WaitSet_init(WaitSetObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {
    "context", "subscriptions", "guard_conditions", "timers", "clients", "services", "events", NULL};
  unsigned long long context;
  PyObject * given[WS_KINDS] = {NULL, NULL, NULL, NULL, NULL, NULL};
  PyObject * empty;
  rcl_ret_t ret;
  int kind;
  if (self->initialised) {
    PyErr_SetString(PyExc_RuntimeError, "WaitSet is initialised once");
    return -1;
  }
  if (!PyArg_ParseTupleAndKeywords(
      args, kwargs, "K|$OOOOOO", keywords, &context, &given[WS_SUBSCRIPTIONS], &given[WS_GUARDS],
      &given[WS_TIMERS], &given[WS_CLIENTS], &given[WS_SERVICES], &given[WS_EVENTS]))
  {
    return -1;
  }
  if (context == 0) {
    PyErr_SetString(PyExc_ValueError, "context must be an rcl context's address");
    return -1;
  }
  empty = PyTuple_New(0);
  if (empty == NULL) {
    return -1;
  }
  for (kind = 0; kind < WS_KINDS; ++kind) {
    if (addresses(given[kind] != NULL ? given[kind] : empty, &self->entities[kind], &self->counts[kind]) < 0) {
      Py_DECREF(empty);
      return -1;
    }
  }
  Py_DECREF(empty);
  self->wait_set = rcl_get_zero_initialized_wait_set();
  ret = rcl_wait_set_init(
    &self->wait_set, self->counts[WS_SUBSCRIPTIONS], self->counts[WS_GUARDS], self->counts[WS_TIMERS],
    self->counts[WS_CLIENTS], self->counts[WS_SERVICES], self->counts[WS_EVENTS],
    (rcl_context_t *)(uintptr_t)context, rcl_get_default_allocator());
  if (ret != RCL_RET_OK) {
    PyErr_Format(PyExc_RuntimeError, "rcl_wait_set_init failed: %s", rcl_get_error_string().str);
    rcl_reset_error();
    return -1;
  }
  self->initialised = 1;
  return 0;
}

static void WaitSet_dealloc(WaitSetObject * self)
{
  int kind;
  if (self->initialised && rcl_wait_set_fini(&self->wait_set) != RCL_RET_OK) {
    rcl_reset_error();
  }
  for (kind = 0; kind < WS_KINDS; ++kind) {
    free(self->entities[kind]);
  }
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static rcl_ret_t fill(WaitSetObject * self)
{
  rcl_wait_set_t * ws = &self->wait_set;
  rcl_ret_t ret = rcl_wait_set_clear(ws);
  size_t i;
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_SUBSCRIPTIONS]; ++i) {
    ret = rcl_wait_set_add_subscription(ws, self->entities[WS_SUBSCRIPTIONS][i], NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_GUARDS]; ++i) {
    ret = rcl_wait_set_add_guard_condition(ws, self->entities[WS_GUARDS][i], NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_TIMERS]; ++i) {
    ret = rcl_wait_set_add_timer(ws, self->entities[WS_TIMERS][i], NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_CLIENTS]; ++i) {
    ret = rcl_wait_set_add_client(ws, self->entities[WS_CLIENTS][i], NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_SERVICES]; ++i) {
    ret = rcl_wait_set_add_service(ws, self->entities[WS_SERVICES][i], NULL);
  }
  for (i = 0; ret == RCL_RET_OK && i < self->counts[WS_EVENTS]; ++i) {
    ret = rcl_wait_set_add_event(ws, self->entities[WS_EVENTS][i], NULL);
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

static PyObject * WaitSet_wait(WaitSetObject * self, PyObject * arg)
{
  long long timeout = PyLong_AsLongLong(arg);
  rcl_wait_set_t * ws = &self->wait_set;
  rcl_ret_t ret;
  if (timeout == -1 && PyErr_Occurred()) {
    return NULL;
  }
  if (!self->initialised) {
    PyErr_SetString(PyExc_RuntimeError, "WaitSet not initialised");
    return NULL;
  }
  ret = fill(self);
  if (ret == RCL_RET_OK) {
    Py_BEGIN_ALLOW_THREADS
    ret = rcl_wait(ws, (int64_t)timeout);
    Py_END_ALLOW_THREADS
  }
  if (ret == RCL_RET_TIMEOUT) {
    /* Nothing ready: rcl cleared every slot. */
    return Py_BuildValue("()");
  }
  if (ret != RCL_RET_OK) {
    PyErr_Format(PyExc_RuntimeError, "rcl_wait failed: %s", rcl_get_error_string().str);
    rcl_reset_error();
    return NULL;
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
  {"wait", (PyCFunction)WaitSet_wait, METH_O,
   "wait(timeout_ns) -> () on timeout, else the ready addresses: (subscriptions, guard_conditions, "
   "timers, clients, services, events)"},
  {NULL, NULL, 0, NULL},
};

static PyTypeObject WaitSetType = {
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

/* ------------------------------------------------------------------------ */
typedef void * (*create_message_t)(void);
typedef void (*destroy_message_t)(void *);
typedef PyObject * (*convert_to_py_t)(void *);

typedef struct {
  PyObject_HEAD
  const rcl_subscription_t * subscription;
  void * message;
  destroy_message_t destroy;
  convert_to_py_t to_py;
} TakerObject;

static void * capsule_of(PyObject * type, const char * name)
{
  void * pointer;
  PyObject * capsule = PyObject_GetAttrString(type, name);
  if (capsule == NULL) {
    return NULL;
  }
  pointer = PyCapsule_GetPointer(capsule, NULL);
  Py_DECREF(capsule);
  return pointer;
}

static int Taker_init(TakerObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"subscription", "message_type", NULL};
  unsigned long long subscription;
  PyObject * type;
  create_message_t create;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "KO", keywords, &subscription, &type)) {
    return -1;
  }
  if (subscription == 0 || self->message != NULL) {
    PyErr_SetString(PyExc_ValueError, "Taker needs an rcl subscription's address, once");
    return -1;
  }
  create = (create_message_t)capsule_of(type, "_CREATE_ROS_MESSAGE");
  if (create == NULL) {
    return -1;
  }
  self->destroy = (destroy_message_t)capsule_of(type, "_DESTROY_ROS_MESSAGE");
  if (self->destroy == NULL) {
    return -1;
  }
  self->to_py = (convert_to_py_t)capsule_of(type, "_CONVERT_TO_PY");
  if (self->to_py == NULL) {
    return -1;
  }
  self->message = create();
  if (self->message == NULL) {
    PyErr_NoMemory();
    return -1;
  }
  self->subscription = (const rcl_subscription_t *)(uintptr_t)subscription;
  return 0;
}

static void Taker_dealloc(TakerObject * self)
{
  if (self->message != NULL) {
    self->destroy(self->message);
  }
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject * sequence_or_none(uint64_t value)
{
  if (value == RMW_MESSAGE_INFO_SEQUENCE_NUMBER_UNSUPPORTED) {
    Py_RETURN_NONE;
  }
  return PyLong_FromUnsignedLongLong(value);
}

/* One message: None when there is none, else the message, or with info
 * (message, info) with rclpy's keys. */
static PyObject * take(TakerObject * self, int with_info)
{
  rmw_message_info_t info = rmw_get_zero_initialized_message_info();
  rcl_ret_t ret;
  PyObject * message;
  PyObject * dict;
  if (self->message == NULL) {
    PyErr_SetString(PyExc_RuntimeError, "Taker not initialised");
    return NULL;
  }
  ret = rcl_take(self->subscription, self->message, &info, NULL);
  if (ret == RCL_RET_SUBSCRIPTION_TAKE_FAILED) {
    Py_RETURN_NONE;
  }
  if (ret != RCL_RET_OK) {
    PyErr_Format(PyExc_RuntimeError, "rcl_take failed: %s", rcl_get_error_string().str);
    rcl_reset_error();
    return NULL;
  }
  message = self->to_py(self->message);
  if (message == NULL || !with_info) {
    return message;
  }
  dict = Py_BuildValue(
    "{s:L,s:L,s:N,s:N}",
    "source_timestamp", (long long)info.source_timestamp,
    "received_timestamp", (long long)info.received_timestamp,
    "publication_sequence_number", sequence_or_none(info.publication_sequence_number),
    "reception_sequence_number", sequence_or_none(info.reception_sequence_number));
  if (dict == NULL) {
    Py_DECREF(message);
    return NULL;
  }
  return Py_BuildValue("(NN)", message, dict);
}

static PyObject * Taker_take(TakerObject * self, PyObject * Py_UNUSED(ignored))
{
  return take(self, 0);
}

static PyObject * Taker_take_with_info(TakerObject * self, PyObject * Py_UNUSED(ignored))
{
  return take(self, 1);
}

static PyMethodDef Taker_methods[] = {
  {"take", (PyCFunction)Taker_take, METH_NOARGS, "take() -> message | None"},
  {"take_with_info", (PyCFunction)Taker_take_with_info, METH_NOARGS,
   "take_with_info() -> (message, info) | None, info as rclpy's take_message gives it"},
  {NULL, NULL, 0, NULL},
};

static PyTypeObject TakerType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Taker",
  .tp_doc = "rcl_take of one subscription, converted with its message type's capsules.",
  .tp_basicsize = sizeof(TakerObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)Taker_init,
  .tp_dealloc = (destructor)Taker_dealloc,
  .tp_methods = Taker_methods,
};

static struct PyModuleDef module = {
  PyModuleDef_HEAD_INIT,
  .m_name = "_fastpath",
  .m_doc = "The executor's hot path: readiness and takes of rcl entities (see the C source for why).",
  .m_size = -1,
};

PyMODINIT_FUNC PyInit__fastpath(void)
{
  PyObject * m;
  if (PyType_Ready(&NotifierType) < 0 || PyType_Ready(&TakerType) < 0 || PyType_Ready(&WaitSetType) < 0) {
    return NULL;
  }
  m = PyModule_Create(&module);
  if (m == NULL) {
    return NULL;
  }
  Py_INCREF(&NotifierType);
  Py_INCREF(&TakerType);
  Py_INCREF(&WaitSetType);
  if (PyModule_AddObject(m, "Notifier", (PyObject *)&NotifierType) < 0 ||
      PyModule_AddObject(m, "Taker", (PyObject *)&TakerType) < 0 ||
      PyModule_AddObject(m, "WaitSet", (PyObject *)&WaitSetType) < 0 ||
      PyModule_AddIntConstant(m, "SUBSCRIPTION", KIND_SUBSCRIPTION) < 0 ||
      PyModule_AddIntConstant(m, "CLIENT", KIND_CLIENT) < 0 ||
      PyModule_AddIntConstant(m, "SERVICE", KIND_SERVICE) < 0 ||
      PyModule_AddIntConstant(m, "EVENT", KIND_EVENT) < 0 ||
      PyModule_AddIntConstant(m, "DRAIN", (long)DRAIN) < 0) {
    Py_DECREF(&NotifierType);
    Py_DECREF(&TakerType);
    Py_DECREF(&WaitSetType);
    Py_DECREF(m);
    return NULL;
  }
  return m;
}
