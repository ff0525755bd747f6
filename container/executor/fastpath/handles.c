/* HandleMeter: the event loop's call_soon and call_at, which meter what a node's code schedules.
 *
 * The executor's own loop (container/executor/_loop.py) credits each handle
 * to the node whose code scheduled it: the node is in the context the
 * handle is scheduled in (a ContextVar, see _owners.py), and its callback
 * is scheduled wrapped in that node's Meter.call. asyncio schedules every
 * wake-up of every task through the loop's call_soon: that is the loop's
 * hottest method, and a Python override of it cost about 1 us a call on
 * this project's VM (a byte bounced between two nodes' asyncio streams, 6%
 * of a round trip's CPU). call_at is next: every sleep of every task and
 * every timeout schedules through it. These are those overrides, in C: a
 * loop class takes this type as its first base, the loop's own class second.
 *
 * A call goes through unchanged when the context names the executor's own
 * work, or when the callback is a step or a wake-up of an asyncio task (its
 * __self__ is a Task: each step of a node's task is metered by the task
 * factory, and a lane's runner task carries callbacks metered already).
 * Otherwise it is scheduled as account.call(arrived, callback, *args),
 * where account = owner.account("loop_callback") and owner is the node's
 * (the unattributed owner when the context names nobody, or is not a
 * contextvars.Context), and arrived is now: its lateness is its wait for
 * the loop. call_at alike (never a task's step), with the account of
 * "loop_timer" and its due time as arrived (the loop's clock is
 * time.monotonic(); 0 when it is no finite number).
 *
 * The accounts of the last KEPT_SLOTS owners seen are kept per kind, the
 * oldest let go first (ten nodes' tasks sleeping in turn missed a cache of
 * one, a Python call each): an owner's call is then found, by a look along
 * at most KEPT_SLOTS pointers, without asking it. */
#include "fastpath.h"

#include <math.h>

#define KEPT_SLOTS 16

/* One owner seen, and its account's call. */
typedef struct {
  PyObject * owner; /* held: its account's call stays its */
  PyObject * call;  /* that owner's account.call */
} KeptSlot;

/* One kind of handle: its account's name, and the calls of the owners seen last. */
typedef struct {
  const char * kind;
  KeptSlot slots[KEPT_SLOTS];
  int next; /* the slot filled next: the oldest */
} Kept;

static int kept_traverse(Kept * kept, visitproc visit, void * arg)
{
  int i;
  for (i = 0; i < KEPT_SLOTS; ++i) {
    Py_VISIT(kept->slots[i].owner);
    Py_VISIT(kept->slots[i].call);
  }
  return 0;
}

static void kept_clear(Kept * kept)
{
  int i;
  kept->next = 0;
  for (i = 0; i < KEPT_SLOTS; ++i) {
    Py_CLEAR(kept->slots[i].owner);
    Py_CLEAR(kept->slots[i].call);
  }
}

typedef struct {
  PyObject_HEAD
  PyObject * owner;        /* the ContextVar naming whose code runs */
  PyObject * executor;     /* its value in the executor's own work */
  PyObject * task_type;    /* asyncio.Task */
  PyObject * call_soon;    /* the loop's own call_soon, unbound */
  PyObject * call_at;      /* the loop's own call_at, unbound */
  PyObject * unattributed; /* the owner of work nobody's context names */
  PyObject * self_name;    /* "__self__", interned */
  Kept soon, at;
} HandleMeterObject;

#define USAGE "HandleMeter(owner: ContextVar, executor, task_type: type, call_soon: callable, call_at: callable, " \
              "unattributed)"

/* HandleMeter(owner, executor, task_type, call_soon, call_at, unattributed) */
static int HandleMeter_init(HandleMeterObject * self, PyObject * args, PyObject * kwargs)
{
  PyObject * owner, * executor, * task_type, * call_soon, * call_at, * unattributed;
  if (kwargs != NULL && PyDict_GET_SIZE(kwargs) > 0) {
    PyErr_SetString(PyExc_TypeError, USAGE);
    return -1;
  }
  if (!PyArg_ParseTuple(
        args, "OOOOOO:HandleMeter", &owner, &executor, &task_type, &call_soon, &call_at, &unattributed)) {
    return -1;
  }
  if (!PyContextVar_CheckExact(owner) || !PyType_Check(task_type) || !PyCallable_Check(call_soon) ||
      !PyCallable_Check(call_at)) {
    PyErr_SetString(PyExc_TypeError, USAGE);
    return -1;
  }
  /* First: initialised() is told by call_soon, set below. */
  if (self->self_name == NULL && (self->self_name = PyUnicode_InternFromString("__self__")) == NULL) {
    return -1;
  }
  Py_XSETREF(self->owner, Py_NewRef(owner));
  Py_XSETREF(self->executor, Py_NewRef(executor));
  Py_XSETREF(self->task_type, Py_NewRef(task_type));
  Py_XSETREF(self->call_soon, Py_NewRef(call_soon));
  Py_XSETREF(self->call_at, Py_NewRef(call_at));
  Py_XSETREF(self->unattributed, Py_NewRef(unattributed));
  self->soon.kind = "loop_callback";
  self->at.kind = "loop_timer";
  kept_clear(&self->soon);
  kept_clear(&self->at);
  return 0;
}

static int HandleMeter_traverse(HandleMeterObject * self, visitproc visit, void * arg)
{
  Py_VISIT(self->owner);
  Py_VISIT(self->executor);
  Py_VISIT(self->task_type);
  Py_VISIT(self->call_soon);
  Py_VISIT(self->call_at);
  Py_VISIT(self->unattributed);
  {
    int visited = kept_traverse(&self->soon, visit, arg);
    return visited != 0 ? visited : kept_traverse(&self->at, visit, arg);
  }
}

static int HandleMeter_clear(HandleMeterObject * self)
{
  Py_CLEAR(self->owner);
  Py_CLEAR(self->executor);
  Py_CLEAR(self->task_type);
  Py_CLEAR(self->call_soon);
  Py_CLEAR(self->call_at);
  Py_CLEAR(self->unattributed);
  Py_CLEAR(self->self_name);
  kept_clear(&self->soon);
  kept_clear(&self->at);
  return 0;
}

/* owner's account of kept's kind: its call (a new reference), kept for next time. */
static PyObject * account_call(HandleMeterObject * self, Kept * kept, PyObject * owner)
{
  PyObject * account, * call, * old_owner, * old_call;
  KeptSlot * slot;
  int i;
  if (owner == Py_None) {
    owner = self->unattributed;
  }
  for (i = 0; i < KEPT_SLOTS; ++i) {
    if (kept->slots[i].owner == owner && kept->slots[i].call != NULL) {
      return Py_NewRef(kept->slots[i].call);
    }
  }
  account = PyObject_CallMethod(owner, "account", "s", kept->kind);
  if (account == NULL) {
    return NULL;
  }
  call = PyObject_GetAttrString(account, "call");
  Py_DECREF(account);
  if (call == NULL) {
    return NULL;
  }
  /* owner.account ran Python code: the slot is chosen only now, and filled whole before
   * the pair it held is let go (which may run code that looks here again). */
  slot = &kept->slots[kept->next];
  kept->next = (kept->next + 1) % KEPT_SLOTS;
  old_owner = slot->owner;
  old_call = slot->call;
  slot->owner = Py_NewRef(owner);
  slot->call = Py_NewRef(call);
  Py_XDECREF(old_owner);
  Py_XDECREF(old_call);
  return call;
}

/* A Python subclass's instance (the loop) comes here through its own dealloc, which then lets
 * go of its type itself. */
static void HandleMeter_dealloc(HandleMeterObject * self)
{
  PyObject_GC_UnTrack(self);
  HandleMeter_clear(self);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

/* Whether callback is a step or wake-up of a task: its __self__ is one (as getattr(callback,
 * "__self__", None) says; bound methods, builtin methods and functions without a lookup). -1: error.
 *
 * A lookup that finds nothing costs an AttributeError, its message formatted and thrown away:
 * a function scheduled by a node (asyncio.gather's and asyncio.wait's done-callbacks, a lambda)
 * cost 1,170 ns a call_soon against 390 ns on a loop without accounting. A function has a
 * __self__ only in its own __dict__ (its type has none), which is looked at directly. */
static int steps_a_task(HandleMeterObject * self, PyObject * callback)
{
  PyObject * bound, * attributes;
  int is_task;
  if (PyMethod_Check(callback)) {
    return PyObject_TypeCheck(PyMethod_GET_SELF(callback), (PyTypeObject *)self->task_type);
  }
  if (PyCFunction_Check(callback)) {
    bound = PyCFunction_GET_SELF(callback);
    return bound != NULL && PyObject_TypeCheck(bound, (PyTypeObject *)self->task_type);
  }
  if (PyFunction_Check(callback)) {
    if ((attributes = PyObject_GenericGetDict(callback, NULL)) == NULL) {
      return -1;
    }
    bound = PyDict_GetItemWithError(attributes, self->self_name); /* borrowed */
    is_task = bound != NULL ? PyObject_TypeCheck(bound, (PyTypeObject *)self->task_type) : PyErr_Occurred() ? -1 : 0;
    Py_DECREF(attributes);
    return is_task;
  }
  bound = PyObject_GetAttr(callback, self->self_name);
  if (bound == NULL) {
    if (!PyErr_ExceptionMatches(PyExc_AttributeError)) {
      return -1;
    }
    PyErr_Clear();
    return 0;
  }
  is_task = PyObject_TypeCheck(bound, (PyTypeObject *)self->task_type);
  Py_DECREF(bound);
  return is_task;
}

/* The owner the context names (a new reference; None: nobody), or NULL on error. */
static PyObject * owner_in(HandleMeterObject * self, PyObject * context)
{
  PyObject * owner;
  if (context == NULL || context == Py_None) {
    if (PyContextVar_Get(self->owner, Py_None, &owner) < 0) {
      return NULL;
    }
    return owner;
  }
  if (!PyContext_CheckExact(context)) {
    return Py_NewRef(Py_None);
  }
  owner = PyObject_GetItem(context, self->owner);
  if (owner == NULL && PyErr_ExceptionMatches(PyExc_KeyError)) {
    PyErr_Clear();
    return Py_NewRef(Py_None);
  }
  return owner;
}

/* The loop's own method own, called with self, first (if any), before, then the arguments in args
 * (nargs of them, then kwnames' values). */
static PyObject * schedule(HandleMeterObject * self, PyObject * own, PyObject * first, PyObject * const * args,
                           Py_ssize_t nargs, PyObject * kwnames, PyObject * const * before, Py_ssize_t nbefore)
{
  PyObject * local[12];
  PyObject ** stack = local;
  PyObject * result;
  Py_ssize_t nkw = kwnames != NULL ? PyTuple_GET_SIZE(kwnames) : 0;
  Py_ssize_t head = first != NULL ? 2 : 1;
  Py_ssize_t total = head + nbefore + nargs + nkw, i;
  if (total > (Py_ssize_t)(sizeof(local) / sizeof(local[0]))) {
    stack = PyMem_Malloc((size_t)total * sizeof(PyObject *));
    if (stack == NULL) {
      return PyErr_NoMemory();
    }
  }
  stack[0] = (PyObject *)self;
  if (first != NULL) {
    stack[1] = first;
  }
  for (i = 0; i < nbefore; ++i) {
    stack[head + i] = before[i];
  }
  for (i = 0; i < nargs + nkw; ++i) {
    stack[head + nbefore + i] = args[i];
  }
  result = PyObject_Vectorcall(own, stack, (size_t)(head + nbefore + nargs), kwnames);
  if (stack != local) {
    PyMem_Free(stack);
  }
  return result;
}

/* The context keyword's value among kwnames (borrowed; NULL: not given). */
static PyObject * context_of(PyObject * const * args, Py_ssize_t nargs, PyObject * kwnames)
{
  Py_ssize_t i, nkw = kwnames != NULL ? PyTuple_GET_SIZE(kwnames) : 0;
  for (i = 0; i < nkw; ++i) {
    if (PyUnicode_CompareWithASCIIString(PyTuple_GET_ITEM(kwnames, i), "context") == 0) {
      return args[nargs + i];
    }
  }
  return NULL;
}

static int initialised(HandleMeterObject * self)
{
  if (self->call_soon == NULL) {
    PyErr_SetString(PyExc_TypeError, "HandleMeter.__init__ was not called");
    return 0;
  }
  return 1;
}

/* call_soon(callback, *args, context=None) -> Handle */
static PyObject * HandleMeter_call_soon(HandleMeterObject * self, PyObject * const * args, Py_ssize_t nargs,
                                        PyObject * kwnames)
{
  PyObject * owner, * call, * arrived, * result;
  PyObject * before[2];
  int is_task;
  if (!initialised(self)) {
    return NULL;
  }
  if (nargs < 1) {
    /* the loop's own call_soon says what is missing */
    return schedule(self, self->call_soon, NULL, args, nargs, kwnames, NULL, 0);
  }
  /* A task's step first: the commonest handle, told without a look at the context. */
  is_task = steps_a_task(self, args[0]);
  if (is_task != 0) {
    return is_task < 0 ? NULL : schedule(self, self->call_soon, NULL, args, nargs, kwnames, NULL, 0);
  }
  owner = owner_in(self, context_of(args, nargs, kwnames));
  if (owner == NULL) {
    return NULL;
  }
  if (owner == self->executor) {
    Py_DECREF(owner);
    return schedule(self, self->call_soon, NULL, args, nargs, kwnames, NULL, 0);
  }
  call = account_call(self, &self->soon, owner);
  Py_DECREF(owner);
  if (call == NULL) {
    return NULL;
  }
  arrived = PyLong_FromLongLong(monotonic_ns());
  if (arrived == NULL) {
    Py_DECREF(call);
    return NULL;
  }
  before[0] = call;
  before[1] = arrived;
  result = schedule(self, self->call_soon, NULL, args, nargs, kwnames, before, 2);
  Py_DECREF(call);
  Py_DECREF(arrived);
  return result;
}

/* call_at(when, callback, *args, context=None) -> TimerHandle */
static PyObject * HandleMeter_call_at(HandleMeterObject * self, PyObject * const * args, Py_ssize_t nargs,
                                      PyObject * kwnames)
{
  PyObject * owner, * call, * arrived, * result;
  PyObject * before[2];
  double when;
  if (!initialised(self)) {
    return NULL;
  }
  if (nargs < 2) {
    /* the loop's own call_at says what is missing */
    return schedule(self, self->call_at, NULL, args, nargs, kwnames, NULL, 0);
  }
  owner = owner_in(self, context_of(args, nargs, kwnames));
  if (owner == NULL) {
    return NULL;
  }
  if (owner == self->executor) {
    Py_DECREF(owner);
    return schedule(self, self->call_at, NULL, args, nargs, kwnames, NULL, 0);
  }
  call = account_call(self, &self->at, owner);
  Py_DECREF(owner);
  if (call == NULL) {
    return NULL;
  }
  when = PyFloat_AsDouble(args[0]);
  if (when == -1.0 && PyErr_Occurred()) {
    PyErr_Clear(); /* no number: the loop's own call_at has its say */
    when = 0.0;
  }
  arrived = PyLong_FromLongLong(isfinite(when) && fabs(when) < 9e9 ? (long long)(when * 1e9) : 0);
  if (arrived == NULL) {
    Py_DECREF(call);
    return NULL;
  }
  before[0] = call;
  before[1] = arrived;
  result = schedule(self, self->call_at, args[0], args + 1, nargs - 1, kwnames, before, 2);
  Py_DECREF(call);
  Py_DECREF(arrived);
  return result;
}

static PyMethodDef HandleMeter_methods[] = {
  {"call_soon", (PyCFunction)(void (*)(void))HandleMeter_call_soon, METH_FASTCALL | METH_KEYWORDS,
   "call_soon(callback, *args, context=None) -> Handle: the loop's own, a node's handle metered as its "
   "(see container/executor/_loop.py)"},
  {"call_at", (PyCFunction)(void (*)(void))HandleMeter_call_at, METH_FASTCALL | METH_KEYWORDS,
   "call_at(when, callback, *args, context=None) -> TimerHandle: the loop's own, a node's timer metered as its, "
   "late from when"},
  {NULL, NULL, 0, NULL},
};

PyTypeObject HandleMeterType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.HandleMeter",
  .tp_doc = "HandleMeter(owner, executor, task_type, call_soon, call_at, unattributed): the first base of an "
            "event loop whose call_soon and call_at meter each handle a node's code schedules as that node's.",
  .tp_basicsize = sizeof(HandleMeterObject),
  .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_BASETYPE | Py_TPFLAGS_HAVE_GC,
  /* tp_new: object's, set by the module (handle_meter_ready): it gives a Python subclass's
   * instance (the loop) its dictionary's inline values, as a plain Python class's instance has;
   * PyType_GenericNew does not, and every attribute the loop's own Python code reads (about a
   * hundred a round trip of a byte over asyncio streams) went the slow way: 4-8% of it. */
  .tp_init = (initproc)HandleMeter_init,
  .tp_dealloc = (destructor)HandleMeter_dealloc,
  .tp_traverse = (traverseproc)HandleMeter_traverse,
  .tp_clear = (inquiry)HandleMeter_clear,
  .tp_methods = HandleMeter_methods,
};

int handle_meter_ready(void)
{
  HandleMeterType.tp_new = PyBaseObject_Type.tp_new;
  return PyType_Ready(&HandleMeterType);
}
