/* lanes.c: what a callback group's lane is, as both languages read it.
 *
 * Work (one callback invocation), Token (whether an entity's work may still
 * start), Runner (a lane's runner task, the future it idles on and the
 * context it runs in), KeepLast (work waiting, bounded per entity like a DDS
 * keep-last history), Slots (a lane's admission state: how many run, the
 * limit, what waits, the idle runners), Route (what the async chain needs of
 * one entity, resolved once per wait-set change) and Routes (the wait set's
 * current routes and its dirty and closed flags).
 *
 * Why compiled: the async chain (express.c) admits a message into its lane,
 * runs its first step in an idle runner and releases the lane for every
 * message, and the Python lane does the same for every other callback. One
 * admission protocol, kept here, serves both: Python calls these methods
 * under the lane's lock; express.c reads the same fields directly while
 * the lock is free (it holds the GIL and calls no Python code in between),
 * so neither side depends on the other's attribute names.
 */
#include "fastpath.h"

#include <structmember.h>

/* -- Token ------------------------------------------------------------------ */

static int Token_init(TokenObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"node", "retired", NULL};
  PyObject * node;
  int retired = 0;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "O|p:Token", keywords, &node, &retired)) {
    return -1;
  }
  Py_XSETREF(self->node, Py_NewRef(node));
  self->retired = (char)retired;
  return 0;
}

static int Token_traverse(TokenObject * self, visitproc visit, void * arg)
{
  Py_VISIT(self->node);
  return 0;
}

static int Token_clear(TokenObject * self)
{
  Py_CLEAR(self->node);
  return 0;
}

static void Token_dealloc(TokenObject * self)
{
  PyObject_GC_UnTrack(self);
  Token_clear(self);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyMemberDef Token_members[] = {
  {"node", T_OBJECT, offsetof(TokenObject, node), READONLY, "The node whose work this token covers."},
  {"retired", T_BOOL, offsetof(TokenObject, retired), 0, "Once true, the work never starts."},
  {NULL, 0, 0, 0, NULL},
};

PyTypeObject TokenType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Token",
  .tp_doc = "Token(node, retired=False): whether work of one entity (or of a node itself) may still start.",
  .tp_basicsize = sizeof(TokenObject),
  .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)Token_init,
  .tp_dealloc = (destructor)Token_dealloc,
  .tp_traverse = (traverseproc)Token_traverse,
  .tp_clear = (inquiry)Token_clear,
  .tp_members = Token_members,
};

/* -- Work ------------------------------------------------------------------- */

static int Work_init(WorkObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {
    "entity", "call", "is_async", "depth", "done", "token", "args", "meter", "arrived", "started", NULL};
  PyObject * entity, * call, * done, * token = Py_None, * call_args = NULL, * meter = Py_None;
  long long arrived = 0, started = 0;
  int is_async;
  Py_ssize_t depth;
  if (!PyArg_ParseTupleAndKeywords(
        args, kwargs, "OOpnO|OO!$OLL:Work", keywords, &entity, &call, &is_async, &depth, &done, &token,
        &PyTuple_Type, &call_args, &meter, &arrived, &started)) {
    return -1;
  }
  if (token != Py_None && !PyObject_TypeCheck(token, &TokenType)) {
    PyErr_SetString(PyExc_TypeError, "Work: token must be a Token or None");
    return -1;
  }
  if (meter != Py_None && !PyObject_TypeCheck(meter, &MeterType)) {
    PyErr_SetString(PyExc_TypeError, "Work: meter must be a Meter or None");
    return -1;
  }
  Py_XSETREF(self->entity, Py_NewRef(entity));
  Py_XSETREF(self->call, Py_NewRef(call));
  Py_XSETREF(self->done, Py_NewRef(done));
  Py_XSETREF(self->token, Py_NewRef(token));
  Py_XSETREF(self->args, call_args != NULL ? Py_NewRef(call_args) : PyTuple_New(0));
  Py_XSETREF(self->meter, meter != Py_None ? (MeterObject *)Py_NewRef(meter) : NULL);
  /* Stamped only when metered: nothing else reads it. */
  self->arrived = arrived > 0 || self->meter == NULL ? arrived : monotonic_ns();
  self->started = started;
  self->is_async = (char)is_async;
  self->depth = depth;
  return self->args == NULL ? -1 : 0;
}

static int Work_traverse(WorkObject * self, visitproc visit, void * arg)
{
  Py_VISIT(self->entity);
  Py_VISIT(self->call);
  Py_VISIT(self->done);
  Py_VISIT(self->token);
  Py_VISIT(self->args);
  Py_VISIT(self->meter);
  return 0;
}

static int Work_clear(WorkObject * self)
{
  Py_CLEAR(self->entity);
  Py_CLEAR(self->call);
  Py_CLEAR(self->done);
  Py_CLEAR(self->token);
  Py_CLEAR(self->args);
  Py_CLEAR(self->meter);
  return 0;
}

static void Work_dealloc(WorkObject * self)
{
  PyObject_GC_UnTrack(self);
  Work_clear(self);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject * Work_repr(WorkObject * self)
{
  return PyUnicode_FromFormat("Work(entity=%R, is_async=%s, depth=%zd)", self->entity,
                              self->is_async ? "True" : "False", self->depth);
}

/* run(context) -> object: the plain callback, call(*args) in context, timed by its meter. */
static PyObject * Work_run(WorkObject * self, PyObject * context)
{
  PyObject * result;
  long long start = 0;
  if (!PyContext_CheckExact(context)) {
    PyErr_SetString(PyExc_TypeError, "run(context): a contextvars.Context");
    return NULL;
  }
  if (PyContext_Enter(context) < 0) {
    return NULL;
  }
  if (self->meter != NULL) {
    start = self->started = meter_begin(self->meter, self->arrived);
  }
  result = PyObject_Call(self->call, self->args, NULL);
  if (self->meter != NULL) {
    meter_end(self->meter, start, start);
  }
  if (PyContext_Exit(context) < 0) {
    Py_XDECREF(result);
    return NULL;
  }
  return result;
}

/* step(send, value) -> object: one step of the async callback's coroutine
 * (send is its send or throw), timed by its meter: the first step begins it,
 * a step that raises (StopIteration included) ends it. */
static PyObject * Work_step(WorkObject * self, PyObject * const * args, Py_ssize_t nargs)
{
  PyObject * result;
  long long start;
  MeterObject * meter = self->meter;
  if (nargs != 2) {
    PyErr_SetString(PyExc_TypeError, "step(send, value)");
    return NULL;
  }
  if (meter == NULL) {
    return PyObject_CallOneArg(args[0], args[1]);
  }
  if (self->started == 0) {
    start = self->started = meter_begin(meter, self->arrived);
  } else {
    start = meter_resume(meter);
  }
  Py_INCREF(meter); /* the step may drop the last reference to this work */
  result = PyObject_CallOneArg(args[0], args[1]);
  if (result != NULL) {
    meter_pause(meter, start);
  } else {
    meter_end(meter, start, self->started);
  }
  Py_DECREF(meter);
  return result;
}

static PyMethodDef Work_methods[] = {
  {"run", (PyCFunction)Work_run, METH_O, "run(context) -> object: call(*args) in context (a plain callback), metered"},
  {"step", (PyCFunction)(void (*)(void))Work_step, METH_FASTCALL,
   "step(send, value) -> object: send(value), one step of the async callback's coroutine, metered"},
  {NULL, NULL, 0, NULL},
};

static PyObject * Work_get_meter(WorkObject * self, void * Py_UNUSED(closure))
{
  return Py_NewRef(self->meter != NULL ? (PyObject *)self->meter : Py_None);
}

static PyGetSetDef Work_getset[] = {
  {"meter", (getter)Work_get_meter, NULL, "What its callbacks cost is told (a Meter, or None).", NULL},
  {NULL, NULL, NULL, NULL, NULL},
};

static PyMemberDef Work_members[] = {
  {"entity", T_OBJECT, offsetof(WorkObject, entity), READONLY, "The rclpy entity whose callback this is (identity only)."},
  {"call", T_OBJECT, offsetof(WorkObject, call), READONLY, "Runs the callback with args; returns a coroutine when is_async."},
  {"is_async", T_BOOL, offsetof(WorkObject, is_async), READONLY, "Whether call returns a coroutine."},
  {"depth", T_PYSSIZET, offsetof(WorkObject, depth), READONLY, "How many waiting invocations of entity to keep."},
  {"done", T_OBJECT, offsetof(WorkObject, done), READONLY, "done(work, error): told the outcome where call ran."},
  {"token", T_OBJECT, offsetof(WorkObject, token), READONLY, "Whose work this is (a Token, or None)."},
  {"args", T_OBJECT, offsetof(WorkObject, args), READONLY, "What call is called with (a taken message)."},
  {"arrived", T_LONGLONG, offsetof(WorkObject, arrived), READONLY, "When it arrived (monotonic ns; 0: not metered)."},
  {"started", T_LONGLONG, offsetof(WorkObject, started), READONLY, "When its first step started (monotonic ns; 0: not yet, or not metered)."},
  {NULL, 0, 0, 0, NULL},
};

PyTypeObject WorkType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Work",
  .tp_doc = "Work(entity, call, is_async, depth, done, token=None, args=()): one callback invocation.",
  .tp_basicsize = sizeof(WorkObject),
  .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)Work_init,
  .tp_dealloc = (destructor)Work_dealloc,
  .tp_traverse = (traverseproc)Work_traverse,
  .tp_clear = (inquiry)Work_clear,
  .tp_repr = (reprfunc)Work_repr,
  .tp_members = Work_members,
  .tp_methods = Work_methods,
  .tp_getset = Work_getset,
};

/* -- Runner ----------------------------------------------------------------- */

static int Runner_init(RunnerObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"task", "context", "idle", "current", NULL};
  PyObject * task, * context, * idle = Py_None, * current = Py_None;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "OO|OO:Runner", keywords, &task, &context, &idle, &current)) {
    return -1;
  }
  if (!PyContext_CheckExact(context)) {
    PyErr_SetString(PyExc_TypeError, "Runner: context must be a contextvars.Context");
    return -1;
  }
  Py_XSETREF(self->task, Py_NewRef(task));
  Py_XSETREF(self->context, Py_NewRef(context));
  Py_XSETREF(self->idle, Py_NewRef(idle));
  Py_XSETREF(self->current, Py_NewRef(current));
  return 0;
}

static int Runner_traverse(RunnerObject * self, visitproc visit, void * arg)
{
  Py_VISIT(self->task);
  Py_VISIT(self->context);
  Py_VISIT(self->idle);
  Py_VISIT(self->current);
  return 0;
}

static int Runner_clear(RunnerObject * self)
{
  Py_CLEAR(self->task);
  Py_CLEAR(self->context);
  Py_CLEAR(self->idle);
  Py_CLEAR(self->current);
  return 0;
}

static void Runner_dealloc(RunnerObject * self)
{
  PyObject_GC_UnTrack(self);
  Runner_clear(self);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyMemberDef Runner_members[] = {
  {"task", T_OBJECT, offsetof(RunnerObject, task), READONLY, "The runner's asyncio task."},
  {"context", T_OBJECT, offsetof(RunnerObject, context), READONLY, "The context it runs in."},
  {"idle", T_OBJECT, offsetof(RunnerObject, idle), 0, "The future it idles on, or None while busy."},
  {"current", T_OBJECT, offsetof(RunnerObject, current), 0, "The work it carries now, or None."},
  {NULL, 0, 0, 0, NULL},
};

PyTypeObject RunnerType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Runner",
  .tp_doc = "Runner(task, context, idle=None, current=None): a lane's runner task and what it carries.",
  .tp_basicsize = sizeof(RunnerObject),
  .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)Runner_init,
  .tp_dealloc = (destructor)Runner_dealloc,
  .tp_traverse = (traverseproc)Runner_traverse,
  .tp_clear = (inquiry)Runner_clear,
  .tp_members = Runner_members,
};

/* -- KeepLast --------------------------------------------------------------- */
/* Items in arrival order with their entities; an entity keeps at most its
 * depth of them, the oldest of its own going first. ``items`` and
 * ``entities`` are lists read from ``head`` on (popped slots are None until
 * the next compaction). */

static int KeepLast_setup(KeepLastObject * self)
{
  if (self->items == NULL) {
    self->items = PyList_New(0);
    self->entities = PyList_New(0);
    self->counts = PyDict_New();
    self->head = 0;
  }
  return self->items != NULL && self->entities != NULL && self->counts != NULL ? 0 : -1;
}

static PyObject * KeepLast_new(PyTypeObject * type, PyObject * args, PyObject * kwargs)
{
  KeepLastObject * self;
  if ((args != NULL && PyTuple_GET_SIZE(args) != 0) || (kwargs != NULL && PyDict_GET_SIZE(kwargs) != 0)) {
    PyErr_SetString(PyExc_TypeError, "KeepLast() takes no arguments");
    return NULL;
  }
  self = (KeepLastObject *)type->tp_alloc(type, 0);
  if (self != NULL && KeepLast_setup(self) < 0) {
    Py_CLEAR(self);
  }
  return (PyObject *)self;
}

static int KeepLast_traverse(KeepLastObject * self, visitproc visit, void * arg)
{
  Py_VISIT(self->items);
  Py_VISIT(self->entities);
  Py_VISIT(self->counts);
  return 0;
}

static int KeepLast_clear_refs(KeepLastObject * self)
{
  Py_CLEAR(self->items);
  Py_CLEAR(self->entities);
  Py_CLEAR(self->counts);
  return 0;
}

static void KeepLast_dealloc(KeepLastObject * self)
{
  PyObject_GC_UnTrack(self);
  KeepLast_clear_refs(self);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

Py_ssize_t keeplast_size(KeepLastObject * self)
{
  return PyList_GET_SIZE(self->items) - self->head;
}

/* The entity's count changes by delta (its entry goes at zero): 0, or -1. */
static int count_add(KeepLastObject * self, PyObject * key, Py_ssize_t delta, Py_ssize_t * before)
{
  PyObject * value = PyDict_GetItemWithError(self->counts, key);
  Py_ssize_t count = 0;
  if (value != NULL) {
    count = PyLong_AsSsize_t(value);
  }
  if (PyErr_Occurred()) {
    return -1;
  }
  if (before != NULL) {
    *before = count;
  }
  if (delta == 0) {
    return 0;
  }
  if (count + delta <= 0) {
    return value != NULL ? PyDict_DelItem(self->counts, key) : 0;
  }
  value = PyLong_FromSsize_t(count + delta);
  if (value == NULL) {
    return -1;
  }
  count = PyDict_SetItem(self->counts, key, value);
  Py_DECREF(value);
  return (int)count;
}

/* Drop the item at index (absolute, >= head). */
static int remove_at(KeepLastObject * self, Py_ssize_t index)
{
  if (PyList_SetSlice(self->items, index, index + 1, NULL) < 0) {
    return -1;
  }
  return PyList_SetSlice(self->entities, index, index + 1, NULL);
}

/* Append item of entity, keeping at most depth of the entity's: 1 if an
 * older one of it was dropped for this one, 0 if not, -1 on error. */
int keeplast_push(KeepLastObject * self, PyObject * item, PyObject * entity, Py_ssize_t depth)
{
  Py_ssize_t count, i, n;
  int dropped = 0;
  PyObject * key = PyLong_FromVoidPtr(entity);
  if (key == NULL || count_add(self, key, 0, &count) < 0) {
    Py_XDECREF(key);
    return -1;
  }
  if (count >= depth) {
    n = PyList_GET_SIZE(self->entities);
    for (i = self->head; i < n; ++i) {
      if (PyList_GET_ITEM(self->entities, i) == entity) {
        PyObject * older = PyList_GET_ITEM(self->items, i);
        if (PyObject_TypeCheck(older, &WorkType) && PyObject_TypeCheck(item, &WorkType) &&
            ((WorkObject *)older)->arrived > 0 && ((WorkObject *)older)->arrived < ((WorkObject *)item)->arrived) {
          /* The entity's callback has been owed since the older one arrived:
           * its lateness counts from then (a timer's first missed firing). */
          ((WorkObject *)item)->arrived = ((WorkObject *)older)->arrived;
        }
        if (remove_at(self, i) < 0) {
          Py_DECREF(key);
          return -1;
        }
        dropped = 1;
        break;
      }
    }
  }
  if (!dropped && count_add(self, key, 1, NULL) < 0) {
    Py_DECREF(key);
    return -1;
  }
  Py_DECREF(key);
  if (PyList_Append(self->items, item) < 0) {
    return -1;
  }
  if (PyList_Append(self->entities, entity) < 0) {
    PyList_SetSlice(self->items, PyList_GET_SIZE(self->items) - 1, PyList_GET_SIZE(self->items), NULL);
    return -1;
  }
  return dropped;
}

/* The oldest item (new reference), NULL with IndexError when empty. */
PyObject * keeplast_pop(KeepLastObject * self)
{
  PyObject * item, * entity, * key;
  Py_ssize_t n = PyList_GET_SIZE(self->items);
  if (self->head >= n) {
    PyErr_SetString(PyExc_IndexError, "pop from an empty KeepLast");
    return NULL;
  }
  item = Py_NewRef(PyList_GET_ITEM(self->items, self->head));
  entity = PyList_GET_ITEM(self->entities, self->head);
  key = PyLong_FromVoidPtr(entity);
  if (key == NULL || count_add(self, key, -1, NULL) < 0) {
    Py_XDECREF(key);
    Py_DECREF(item);
    return NULL;
  }
  Py_DECREF(key);
  PyList_SetItem(self->items, self->head, Py_NewRef(Py_None));
  PyList_SetItem(self->entities, self->head, Py_NewRef(Py_None));
  self->head++;
  if (self->head == n) {
    if (PyList_SetSlice(self->items, 0, n, NULL) < 0 || PyList_SetSlice(self->entities, 0, n, NULL) < 0) {
      Py_DECREF(item);
      return NULL;
    }
    self->head = 0;
  } else if (self->head >= 64 && self->head * 2 >= n) {
    if (PyList_SetSlice(self->items, 0, self->head, NULL) < 0 ||
        PyList_SetSlice(self->entities, 0, self->head, NULL) < 0) {
      Py_DECREF(item);
      return NULL;
    }
    self->head = 0;
  }
  return item;
}

int keeplast_clear(KeepLastObject * self)
{
  self->head = 0;
  if (PyList_SetSlice(self->items, 0, PyList_GET_SIZE(self->items), NULL) < 0 ||
      PyList_SetSlice(self->entities, 0, PyList_GET_SIZE(self->entities), NULL) < 0) {
    return -1;
  }
  PyDict_Clear(self->counts);
  return 0;
}

/* Take out every item for which keep(item) is 0; they are returned in order
 * (new list). keep returns 1 keep, 0 take out, -1 error. */
static PyObject * keeplast_take_out(KeepLastObject * self, int (*keep)(PyObject *, void *), void * data)
{
  PyObject * out = PyList_New(0);
  Py_ssize_t i = self->head;
  if (out == NULL) {
    return NULL;
  }
  while (i < PyList_GET_SIZE(self->items)) {
    PyObject * item = PyList_GET_ITEM(self->items, i);
    PyObject * entity = PyList_GET_ITEM(self->entities, i);
    PyObject * key;
    int kept = keep(item, data);
    if (kept < 0) {
      Py_DECREF(out);
      return NULL;
    }
    if (kept) {
      ++i;
      continue;
    }
    key = PyLong_FromVoidPtr(entity);
    if (key == NULL || count_add(self, key, -1, NULL) < 0 || PyList_Append(out, item) < 0 || remove_at(self, i) < 0) {
      Py_XDECREF(key);
      Py_DECREF(out);
      return NULL;
    }
    Py_DECREF(key);
  }
  return out;
}

static PyObject * KeepLast_push(KeepLastObject * self, PyObject * const * args, Py_ssize_t nargs)
{
  Py_ssize_t depth;
  int dropped;
  if (nargs != 3) {
    PyErr_SetString(PyExc_TypeError, "push(item, entity, depth)");
    return NULL;
  }
  depth = PyLong_AsSsize_t(args[2]);
  if (depth == -1 && PyErr_Occurred()) {
    return NULL;
  }
  dropped = keeplast_push(self, args[0], args[1], depth);
  return dropped < 0 ? NULL : PyBool_FromLong(dropped);
}

static PyObject * KeepLast_pop(KeepLastObject * self, PyObject * Py_UNUSED(ignored))
{
  return keeplast_pop(self);
}

static PyObject * KeepLast_clear(KeepLastObject * self, PyObject * Py_UNUSED(ignored))
{
  return keeplast_clear(self) < 0 ? NULL : Py_NewRef(Py_None);
}

static Py_ssize_t KeepLast_len(KeepLastObject * self)
{
  return keeplast_size(self);
}

static PyObject * KeepLast_items(KeepLastObject * self, PyObject * Py_UNUSED(ignored))
{
  return PyList_GetSlice(self->items, self->head, PyList_GET_SIZE(self->items));
}

static PyMethodDef KeepLast_methods[] = {
  {"push", (PyCFunction)(void (*)(void))KeepLast_push, METH_FASTCALL,
   "push(item, entity, depth) -> bool: append; True if the entity's oldest item went to keep depth of its own"},
  {"pop", (PyCFunction)KeepLast_pop, METH_NOARGS, "pop() -> the oldest item (IndexError when empty)"},
  {"clear", (PyCFunction)KeepLast_clear, METH_NOARGS, "clear() -> None"},
  {"items", (PyCFunction)KeepLast_items, METH_NOARGS, "items() -> list: what waits, oldest first"},
  {NULL, NULL, 0, NULL},
};

static PySequenceMethods KeepLast_sequence = {
  .sq_length = (lenfunc)KeepLast_len,
};

PyTypeObject KeepLastType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.KeepLast",
  .tp_doc = "KeepLast(): items in arrival order, at most depth per entity, the entity's oldest going first.",
  .tp_basicsize = sizeof(KeepLastObject),
  .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
  .tp_new = KeepLast_new,
  .tp_dealloc = (destructor)KeepLast_dealloc,
  .tp_traverse = (traverseproc)KeepLast_traverse,
  .tp_clear = (inquiry)KeepLast_clear_refs,
  .tp_methods = KeepLast_methods,
  .tp_as_sequence = &KeepLast_sequence,
};

/* -- Slots ------------------------------------------------------------------ */

static PyObject * Slots_new(PyTypeObject * type, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"limit", NULL};
  Py_ssize_t limit;
  SlotsObject * self;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "n:Slots", keywords, &limit)) {
    return NULL;
  }
  if (limit < 1) {
    PyErr_SetString(PyExc_ValueError, "a lane's limit is at least 1");
    return NULL;
  }
  self = (SlotsObject *)type->tp_alloc(type, 0);
  if (self == NULL) {
    return NULL;
  }
  self->limit = limit;
  self->lock = (LockObject *)PyObject_CallNoArgs((PyObject *)&LockType);
  self->pending = (KeepLastObject *)PyObject_CallNoArgs((PyObject *)&KeepLastType);
  self->active = PySet_New(NULL);
  self->idle_runners = PyList_New(0);
  if (self->lock == NULL || self->pending == NULL || self->active == NULL || self->idle_runners == NULL) {
    Py_DECREF(self);
    return NULL;
  }
  return (PyObject *)self;
}

static int Slots_traverse(SlotsObject * self, visitproc visit, void * arg)
{
  Py_VISIT(self->lock);
  Py_VISIT(self->pending);
  Py_VISIT(self->active);
  Py_VISIT(self->idle_runners);
  return 0;
}

static int Slots_clear_refs(SlotsObject * self)
{
  Py_CLEAR(self->lock);
  Py_CLEAR(self->pending);
  Py_CLEAR(self->active);
  Py_CLEAR(self->idle_runners);
  return 0;
}

static void Slots_dealloc(SlotsObject * self)
{
  PyObject_GC_UnTrack(self);
  Slots_clear_refs(self);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

#define AS_WORK(object) ((WorkObject *)(object))

/* Py_False when runner idles on a pending future, Py_True when it does not
 * (None, or done: cancelled while idle), NULL on error; borrowed booleans. */
static PyObject * runner_idle_done(RunnerObject * runner);

static int check_work(PyObject * work)
{
  if (!PyObject_TypeCheck(work, &WorkType)) {
    PyErr_SetString(PyExc_TypeError, "a lane admits Work only");
    return -1;
  }
  return 0;
}

/* admit(work) -> bool: the slot is taken (True), or the work waits, keep-last
 * per entity (False), or the lane is closed (False: dropped). */
static PyObject * Slots_admit(SlotsObject * self, PyObject * work)
{
  int dropped;
  if (check_work(work) < 0) {
    return NULL;
  }
  if (self->closed) {
    Py_RETURN_FALSE;
  }
  if (self->running < self->limit) {
    if (PySet_Add(self->active, work) < 0) {
      return NULL;
    }
    self->running++;
    Py_RETURN_TRUE;
  }
  dropped = keeplast_push(self->pending, work, AS_WORK(work)->entity, AS_WORK(work)->depth);
  if (dropped < 0) {
    return NULL;
  }
  self->dropped += dropped;
  if (dropped && AS_WORK(work)->meter != NULL) {
    AS_WORK(work)->meter->dropped++; /* the dropped one was of the same entity */
  }
  Py_RETURN_FALSE;
}

/* next(finished) -> Work | None: finished is done; its slot goes to the
 * oldest waiting work (returned, to be started) or is given back. */
static PyObject * Slots_next(SlotsObject * self, PyObject * finished)
{
  PyObject * work;
  if (PySet_Discard(self->active, finished) < 0) {
    return NULL;
  }
  if (keeplast_size(self->pending) > 0 && !self->closed) {
    work = keeplast_pop(self->pending);
    if (work == NULL || PySet_Add(self->active, work) < 0) {
      Py_XDECREF(work);
      return NULL;
    }
    return work;
  }
  self->running--;
  Py_RETURN_NONE;
}

static PyObject * Slots_close(SlotsObject * self, PyObject * Py_UNUSED(ignored))
{
  self->closed = 1;
  return keeplast_clear(self->pending) < 0 ? NULL : Py_NewRef(Py_None);
}

static int of_node(PyObject * work, PyObject * node)
{
  PyObject * token = AS_WORK(work)->token;
  return token != NULL && PyObject_TypeCheck(token, &TokenType) && ((TokenObject *)token)->node == node;
}

static int keep_unless_of(PyObject * work, void * node)
{
  return !of_node(work, (PyObject *)node);
}

/* retire(node) -> list[Work]: take the node's waiting work out (to be told it was dropped). */
static PyObject * Slots_retire(SlotsObject * self, PyObject * node)
{
  return keeplast_take_out(self->pending, keep_unless_of, node);
}

/* of(node) -> list[Work]: the node's work started and not yet done. */
static PyObject * Slots_of(SlotsObject * self, PyObject * node)
{
  PyObject * out = PyList_New(0), * iterator, * work;
  if (out == NULL || (iterator = PyObject_GetIter(self->active)) == NULL) {
    Py_XDECREF(out);
    return NULL;
  }
  while ((work = PyIter_Next(iterator)) != NULL) {
    int failed = of_node(work, node) && PyList_Append(out, work) < 0;
    Py_DECREF(work);
    if (failed) {
      Py_DECREF(iterator);
      Py_DECREF(out);
      return NULL;
    }
  }
  Py_DECREF(iterator);
  if (PyErr_Occurred()) {
    Py_DECREF(out);
    return NULL;
  }
  return out;
}

/* activate(work): work whose slot is taken (a suspended first step) counts as started. */
static PyObject * Slots_activate(SlotsObject * self, PyObject * work)
{
  if (check_work(work) < 0 || PySet_Add(self->active, work) < 0) {
    return NULL;
  }
  Py_RETURN_NONE;
}

static int check_runner(PyObject * runner)
{
  if (!PyObject_TypeCheck(runner, &RunnerType)) {
    PyErr_SetString(PyExc_TypeError, "a lane parks Runners only");
    return -1;
  }
  return 0;
}

/* park(runner): it idles; the last parked is used first. */
static PyObject * Slots_park(SlotsObject * self, PyObject * runner)
{
  if (check_runner(runner) < 0 || PyList_Append(self->idle_runners, runner) < 0) {
    return NULL;
  }
  Py_RETURN_NONE;
}

/* unpark(runner) -> bool: taken out of the parked ones (False: it was not parked). */
static PyObject * Slots_unpark(SlotsObject * self, PyObject * runner)
{
  Py_ssize_t i;
  for (i = PyList_GET_SIZE(self->idle_runners) - 1; i >= 0; --i) {
    if (PyList_GET_ITEM(self->idle_runners, i) == runner) {
      if (PyList_SetSlice(self->idle_runners, i, i + 1, NULL) < 0) {
        return NULL;
      }
      Py_RETURN_TRUE;
    }
  }
  Py_RETURN_FALSE;
}

/* idle_runner() -> Runner | None: the last parked runner idling on a pending
 * future, left parked; those whose future is done on the way are dropped. */
static PyObject * Slots_idle_runner(SlotsObject * self, PyObject * Py_UNUSED(ignored))
{
  Py_ssize_t n;
  while ((n = PyList_GET_SIZE(self->idle_runners)) > 0) {
    RunnerObject * runner = (RunnerObject *)Py_NewRef(PyList_GET_ITEM(self->idle_runners, n - 1));
    PyObject * done = runner_idle_done(runner);
    if (done == Py_False) {
      return (PyObject *)runner;
    }
    if (done == NULL) {
      Py_DECREF(runner);
      return NULL;
    }
    /* Still the last one (the call may have run code that parked more)? */
    n = PyList_GET_SIZE(self->idle_runners);
    if (n > 0 && PyList_GET_ITEM(self->idle_runners, n - 1) == (PyObject *)runner &&
        PyList_SetSlice(self->idle_runners, n - 1, n, NULL) < 0) {
      Py_DECREF(runner);
      return NULL;
    }
    if (n == 0 || PyList_GET_ITEM(self->idle_runners, n - 1) != (PyObject *)runner) {
      /* Parked elsewhere in the list now, or gone: take it out wherever it is. */
      PyObject * gone = Slots_unpark(self, (PyObject *)runner);
      if (gone == NULL) {
        Py_DECREF(runner);
        return NULL;
      }
      Py_DECREF(gone);
    }
    Py_DECREF(runner);
  }
  Py_RETURN_NONE;
}

static PyObject * Slots_get_idle(SlotsObject * self, void * Py_UNUSED(closure))
{
  return PyLong_FromSsize_t(PyList_GET_SIZE(self->idle_runners));
}

static PyObject * Slots_busy(SlotsObject * self, PyObject * Py_UNUSED(ignored))
{
  return PyBool_FromLong(self->running > 0 || keeplast_size(self->pending) > 0);
}

static PyObject * Slots_get_waiting(SlotsObject * self, void * Py_UNUSED(closure))
{
  return PyLong_FromSsize_t(keeplast_size(self->pending));
}

static PyObject * Slots_get_limit(SlotsObject * self, void * Py_UNUSED(closure))
{
  return PyLong_FromSsize_t(self->limit);
}

static int Slots_set_limit(SlotsObject * self, PyObject * value, void * Py_UNUSED(closure))
{
  Py_ssize_t limit = value != NULL ? PyLong_AsSsize_t(value) : -1;
  if (limit < 1) {
    if (!PyErr_Occurred()) {
      PyErr_SetString(PyExc_ValueError, "a lane's limit is at least 1");
    }
    return -1;
  }
  self->limit = limit;
  return 0;
}

/* An idle runner whose first step may run now (new reference), its slot
 * taken; Py_None when none may (the lane is locked, closed, full or without
 * an idle runner: the Python path finds or makes one); NULL on error. */
static PyObject * runner_idle_done(RunnerObject * runner)
{
  PyObject * idle = Py_NewRef(runner->idle), * done;
  int is_done;
  if (idle == Py_None) {
    Py_DECREF(idle);
    return Py_True;
  }
  done = PyObject_CallMethod(idle, "done", NULL);
  Py_DECREF(idle);
  if (done == NULL) {
    return NULL;
  }
  is_done = PyObject_IsTrue(done);
  Py_DECREF(done);
  return is_done < 0 ? NULL : is_done ? Py_True : Py_False;
}

PyObject * slots_admit_first_step(SlotsObject * self)
{
  RunnerObject * runner;
  PyObject * done;
  Py_ssize_t n;
  if (self->lock->locked || self->closed || self->running >= self->limit) {
    Py_RETURN_NONE;
  }
  n = PyList_GET_SIZE(self->idle_runners);
  if (n == 0) {
    Py_RETURN_NONE;
  }
  /* Held before anything is called: the call may change the list. */
  runner = (RunnerObject *)Py_NewRef(PyList_GET_ITEM(self->idle_runners, n - 1));
  if ((done = runner_idle_done(runner)) != Py_False) {
    Py_DECREF(runner);
    if (done == NULL) {
      return NULL;
    }
    Py_RETURN_NONE; /* not idle after all: the Python path finds or makes one */
  }
  if (self->lock->locked || self->closed || self->running >= self->limit) {
    Py_DECREF(runner); /* what the call ran took the lane meanwhile */
    Py_RETURN_NONE;
  }
  self->running++;
  return (PyObject *)runner;
}

/* The slot slots_admit_first_step took is given back: 0 done, 1 when the
 * Python lane must do it (its lock is held, or work waits for the slot). */
int slots_release_first_step(SlotsObject * self)
{
  if (self->lock->locked || keeplast_size(self->pending) > 0) {
    return 1;
  }
  self->running--;
  return 0;
}

/* The first step could not even start: its slot is given back as it was taken. */
void slots_undo_first_step(SlotsObject * self)
{
  self->running--;
}

static PyMethodDef Slots_methods[] = {
  {"admit", (PyCFunction)Slots_admit, METH_O,
   "admit(work) -> bool: slot taken; else the work waits (keep-last per entity) or, closed, is dropped"},
  {"next", (PyCFunction)Slots_next, METH_O,
   "next(finished) -> Work | None: finished is done; the oldest waiting work takes its slot, or it is given back"},
  {"close", (PyCFunction)Slots_close, METH_NOARGS, "close() -> None: admit nothing more; what waits is dropped"},
  {"retire", (PyCFunction)Slots_retire, METH_O, "retire(node) -> list[Work]: the node's waiting work, taken out"},
  {"of", (PyCFunction)Slots_of, METH_O, "of(node) -> list[Work]: the node's work started and not yet done"},
  {"busy", (PyCFunction)Slots_busy, METH_NOARGS, "busy() -> bool: something runs or waits"},
  {"activate", (PyCFunction)Slots_activate, METH_O,
   "activate(work) -> None: work whose slot is taken already (a suspended first step) counts as started"},
  {"park", (PyCFunction)Slots_park, METH_O, "park(runner) -> None: it idles; the last parked is used first"},
  {"unpark", (PyCFunction)Slots_unpark, METH_O, "unpark(runner) -> bool: taken out of the parked ones"},
  {"idle_runner", (PyCFunction)Slots_idle_runner, METH_NOARGS,
   "idle_runner() -> Runner | None: the last parked runner idling on a pending future (left parked); "
   "those whose future is done are dropped"},
  {NULL, NULL, 0, NULL},
};

static PyMemberDef Slots_members[] = {
  {"lock", T_OBJECT, offsetof(SlotsObject, lock), READONLY,
   "Held while Python changes the state; the compiled path touches it only while the lock is free."},
  {"running", T_PYSSIZET, offsetof(SlotsObject, running), READONLY, "Slots taken."},
  {"dropped", T_PYSSIZET, offsetof(SlotsObject, dropped), READONLY, "Waiting work dropped for newer of its entity."},
  {"closed", T_BOOL, offsetof(SlotsObject, closed), READONLY, "Closed: nothing is admitted any more."},
  {NULL, 0, 0, 0, NULL},
};

static PyGetSetDef Slots_getset[] = {
  {"limit", (getter)Slots_get_limit, (setter)Slots_set_limit, "How many may run at once.", NULL},
  {"waiting", (getter)Slots_get_waiting, NULL, "How much work waits for a slot.", NULL},
  {"idle", (getter)Slots_get_idle, NULL, "How many runners are parked.", NULL},
  {NULL, NULL, NULL, NULL, NULL},
};

PyTypeObject SlotsType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Slots",
  .tp_doc = "Slots(limit): a lane's admission state; methods are called with its lock held.",
  .tp_basicsize = sizeof(SlotsObject),
  .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
  .tp_new = Slots_new,
  .tp_dealloc = (destructor)Slots_dealloc,
  .tp_traverse = (traverseproc)Slots_traverse,
  .tp_clear = (inquiry)Slots_clear_refs,
  .tp_methods = Slots_methods,
  .tp_members = Slots_members,
  .tp_getset = Slots_getset,
};

/* -- Route ------------------------------------------------------------------ */

static int Route_init(RouteObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"first", "entry", "lane", "slots", "marker", "entity", "token", "callback", NULL};
  PyObject * first, * entry, * lane, * slots, * marker, * entity, * token, * callback;
  if (!PyArg_ParseTupleAndKeywords(
        args, kwargs, "$OOOO!O!OO!U:Route", keywords, &first, &entry, &lane, &SlotsType, &slots, &WorkType,
        &marker, &entity, &TokenType, &token, &callback)) {
    return -1;
  }
  if (self->first != NULL) {
    PyErr_SetString(PyExc_RuntimeError, "Route is initialised once");
    return -1;
  }
  /* A subscription's first is its Taker (which holds the subscription); a
   * timer's is its handle, held here: call_timers reads its pointer. */
  if (!PyObject_TypeCheck(first, &TakerType) && held_enter(&self->timer, first) < 0) {
    return -1;
  }
  Py_XSETREF(self->first, Py_NewRef(first));
  Py_XSETREF(self->entry, Py_NewRef(entry));
  Py_XSETREF(self->lane, Py_NewRef(lane));
  Py_XSETREF(self->slots, (SlotsObject *)Py_NewRef(slots));
  Py_XSETREF(self->marker, Py_NewRef(marker));
  Py_XSETREF(self->entity, Py_NewRef(entity));
  Py_XSETREF(self->token, (TokenObject *)Py_NewRef(token));
  Py_XSETREF(self->callback, Py_NewRef(callback));
  return 0;
}

static int Route_traverse(RouteObject * self, visitproc visit, void * arg)
{
  Py_VISIT(self->first);
  Py_VISIT(self->entry);
  Py_VISIT(self->lane);
  Py_VISIT(self->slots);
  Py_VISIT(self->marker);
  Py_VISIT(self->entity);
  Py_VISIT(self->token);
  Py_VISIT(self->callback);
  return 0;
}

static int Route_clear(RouteObject * self)
{
  Py_CLEAR(self->first);
  Py_CLEAR(self->entry);
  Py_CLEAR(self->lane);
  Py_CLEAR(self->slots);
  Py_CLEAR(self->marker);
  Py_CLEAR(self->entity);
  Py_CLEAR(self->token);
  Py_CLEAR(self->callback);
  return 0;
}

static void Route_dealloc(RouteObject * self)
{
  PyObject_GC_UnTrack(self);
  held_exit(&self->timer);
  Route_clear(self);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyMemberDef Route_members[] = {
  {"first", T_OBJECT, offsetof(RouteObject, first), READONLY, "The subscription's Taker, or the timer's handle (held)."},
  {"entry", T_OBJECT, offsetof(RouteObject, entry), READONLY, "The dispatcher's entry, handed back to its hooks."},
  {"lane", T_OBJECT, offsetof(RouteObject, lane), READONLY, "The lane, handed back to its hooks."},
  {"slots", T_OBJECT, offsetof(RouteObject, slots), READONLY, "The lane's Slots."},
  {"marker", T_OBJECT, offsetof(RouteObject, marker), READONLY, "The Work a runner carries meanwhile (for reports)."},
  {"entity", T_OBJECT, offsetof(RouteObject, entity), READONLY, "The rclpy entity."},
  {"token", T_OBJECT, offsetof(RouteObject, token), READONLY, "The entity's Token."},
  {"callback", T_OBJECT, offsetof(RouteObject, callback), READONLY, "The name of the entity's callback attribute."},
  {NULL, 0, 0, 0, NULL},
};

PyTypeObject RouteType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Route",
  .tp_doc = "Route(*, first, entry, lane, slots, marker, entity, token, callback): what the async chain needs of one entity.",
  .tp_basicsize = sizeof(RouteObject),
  .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)Route_init,
  .tp_dealloc = (destructor)Route_dealloc,
  .tp_traverse = (traverseproc)Route_traverse,
  .tp_clear = (inquiry)Route_clear,
  .tp_members = Route_members,
};

/* -- Routes ----------------------------------------------------------------- */

static PyObject * Routes_new(PyTypeObject * type, PyObject * args, PyObject * kwargs)
{
  RoutesObject * self;
  if ((args != NULL && PyTuple_GET_SIZE(args) != 0) || (kwargs != NULL && PyDict_GET_SIZE(kwargs) != 0)) {
    PyErr_SetString(PyExc_TypeError, "Routes() takes no arguments");
    return NULL;
  }
  self = (RoutesObject *)type->tp_alloc(type, 0);
  if (self == NULL) {
    return NULL;
  }
  self->dirty = 1;
  self->subscriptions = PyDict_New();
  self->timers = PyDict_New();
  if (self->subscriptions == NULL || self->timers == NULL) {
    Py_DECREF(self);
    return NULL;
  }
  return (PyObject *)self;
}

static int Routes_traverse(RoutesObject * self, visitproc visit, void * arg)
{
  Py_VISIT(self->subscriptions);
  Py_VISIT(self->timers);
  return 0;
}

static int Routes_clear(RoutesObject * self)
{
  Py_CLEAR(self->subscriptions);
  Py_CLEAR(self->timers);
  return 0;
}

static void Routes_dealloc(RoutesObject * self)
{
  PyObject_GC_UnTrack(self);
  Routes_clear(self);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

/* A copy of value: what the chain reads is never changed under it. */
static int set_dict(PyObject ** field, PyObject * value)
{
  PyObject * copy;
  if (value == NULL || !PyDict_Check(value)) {
    PyErr_SetString(PyExc_TypeError, "routes are a dict of handle address -> Route");
    return -1;
  }
  if ((copy = PyDict_Copy(value)) == NULL) {
    return -1;
  }
  Py_XSETREF(*field, copy);
  return 0;
}

static PyObject * Routes_get_subscriptions(RoutesObject * self, void * Py_UNUSED(closure))
{
  return Py_NewRef(self->subscriptions);
}

static int Routes_set_subscriptions(RoutesObject * self, PyObject * value, void * Py_UNUSED(closure))
{
  return set_dict(&self->subscriptions, value);
}

static PyObject * Routes_get_timers(RoutesObject * self, void * Py_UNUSED(closure))
{
  return Py_NewRef(self->timers);
}

static int Routes_set_timers(RoutesObject * self, PyObject * value, void * Py_UNUSED(closure))
{
  return set_dict(&self->timers, value);
}

static PyMemberDef Routes_members[] = {
  {"dirty", T_BOOL, offsetof(RoutesObject, dirty), 0, "The entities changed: the routes are stale until rebuilt."},
  {"closed", T_BOOL, offsetof(RoutesObject, closed), 0, "The wait set is closed: nothing is taken."},
  {NULL, 0, 0, 0, NULL},
};

static PyGetSetDef Routes_getset[] = {
  {"subscriptions", (getter)Routes_get_subscriptions, (setter)Routes_set_subscriptions,
   "Async subscriptions the chain takes and runs, by handle address.", NULL},
  {"timers", (getter)Routes_get_timers, (setter)Routes_set_timers,
   "Async timers the chain calls and runs, by handle address.", NULL},
  {NULL, NULL, NULL, NULL, NULL},
};

PyTypeObject RoutesType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Routes",
  .tp_doc = "Routes(): a wait set's current routes, and whether they are stale (dirty) or closed.",
  .tp_basicsize = sizeof(RoutesObject),
  .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
  .tp_new = Routes_new,
  .tp_dealloc = (destructor)Routes_dealloc,
  .tp_traverse = (traverseproc)Routes_traverse,
  .tp_clear = (inquiry)Routes_clear,
  .tp_members = Routes_members,
  .tp_getset = Routes_getset,
};
